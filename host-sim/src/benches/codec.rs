//! `dpsa codec-bench`: the row codec (`dpsa_core::packets::codec`) against general-purpose and
//! MCU-class compressors, the entropy of its own predictor's residuals, and the noise floor.
//!
//! Every method compresses the *same* rows: the rows of a height map that decoded, each `W`
//! i16 heights plus `W` validity bits, invalid heights 0. The raw size of a row is the raw
//! packet payload (codec 0): `ceil(W/8)` validity bytes + `2 W` height bytes, and every
//! `ratio` is `raw bytes / compressed bytes` over all rows:
//!
//! | method | what is compressed |
//! | --- | --- |
//! | `ours` | codec payloads with intra period 1: every row decodable alone (the stream default: one lost packet loses only itself); payloads only |
//! | `ours_framed` | the same plus 44 bytes of packet framing per row (header 40 + CRC 4) and the stream's header and end packets (`STREAM_FRAMING_BYTES`); a stream also carries a 44-byte trigger record per frame, which does not depend on the codec and is not counted here |
//! | `ours_predicted` | codec payloads with intra period 32 (rows predicted from the previous row; a lost packet costs up to 31 more rows) |
//! | `lz4` | `lz4_flex` block compression of each row's raw payload, row by row |
//! | `lz4_stream` | `lz4_flex` block compression of all raw payloads concatenated |
//! | `mcu` | heatshrink ([`MCU_NAME`], no allocation, fixed RAM), row by row |
//! | `zstd3`, `zstd19` | zstd levels 3 and 19 on all raw payloads concatenated (the most favourable case for zstd) |
//! | `png16` | the whole map as one 16-bit grey PNG (best compression, adaptive filter): `h + 32768` where valid, 0 where invalid |
//! | `entropy_bound` | `16 / H`: 16 height bits per valid pixel over `H`, the zeroth-order entropy (one histogram over the whole map) of the intra predictor's residuals at the valid pixels |
//!
//! **Comparing `ours` with the entropy bound.** `entropy_bound` ignores the validity bits (and
//! the row headers and byte padding), and its raw size is 16 bits per *valid* pixel where the
//! other ratios count 17 bits per pixel (16 height bits and 1 validity bit, valid or not), so
//! `ratio.ours` and `ratio.entropy_bound` are not comparable as they stand. Two like-for-like
//! versions (`V` valid pixels, `B` bits of `ours`, `M` of them in validity sections):
//!
//! - `ratio.ours_heights_only = 16 V / (B - M)`: `ours` on the bound's terms, the validity bits
//!   removed from both sides; `ours` is still charged its 2-byte row headers and padding.
//!   `ours_heights_only >= 0.95 entropy_bound` iff `B - M <= V H / 0.95`.
//! - `ratio.entropy_bound_same_raw = raw bits / (V H)`: the bound on the raw size of the other
//!   ratios, the validity free for the bound but not for `ours` (stricter):
//!   `ratio.ours >= f x entropy_bound_same_raw` iff `bits_per_pixel.ours_over_entropy <= 1 / f`.
//!
//! Both charge `ours` for what makes every row decodable alone: 16 header bits and up to 7
//! padding bits per row, and Rice parameters that restart at every row. These weigh about
//! `1 / W`: about 1.6 % of `H` for `W = 256`, 0.4 % for `W = 1024`.
//! `bits_per_pixel.ours_parts` splits `ours` into residual codes, validity, headers and
//! padding, and raw rows. `H` is not a strict lower bound for `ours`: the codec adapts its Rice
//! parameter per context and pixel, and beats a single global histogram where the residual
//! statistics change across the map (board vs paste, edges).
//!
//! `H` is the entropy of *our* predictor: the module does not expose residuals, so
//! [`intra_row`] reproduces the intra predictor of the codec's module docs (filled row `R`,
//! `a = R[c-1]`, `aa = R[c-2]`, average or left neighbour by `|a - aa|`) and, with the
//! validity runs and the adaptive Rice code, the exact payload length. Every row's modelled
//! length must equal the encoder's, or the benchmark fails: the residuals are the codec's.
//!
//! `bits_per_pixel.noise` is what the height noise alone costs any lossless coder: the entropy
//! `log2(sigma sqrt(2 pi e))` of a quantised Gaussian, with `sigma` (LSB) estimated from the
//! horizontal second differences `h[c-1] - 2 h[c] + h[c+1]` of valid pixel triples (variance
//! `6 sigma^2` for white noise) as `1.4826 MAD / sqrt(6)`, the MAD interpolated inside its
//! integer bin. Every method's output is decoded again and compared with the input; a
//! difference fails the benchmark.

use crate::error::chain;
use crate::heightmap::{HeightMap, HeightRow};
use crate::simulation::recording::Recording;
use crate::{progress::progress_bar, reconstruct, stream};
use crate::{At, Result, SimError};
use dpsa_core::packets::codec::{self, Decoder, Encoder};
use heatshrink::decoder::HeatshrinkDecoder;
use heatshrink::encoder::HeatshrinkEncoder;
use heatshrink::{Poll, SinkError};
use indicatif::ProgressBar;
use serde::Serialize;
use std::path::Path;
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

/// Bytes of packet framing per row: header 40 + CRC 4.
pub const FRAMING_BYTES: usize = dpsa_core::packets::HEADER_LEN + dpsa_core::packets::TRAILER_LEN;
/// Bytes of a stream's own packets: the stream header (52) and the end packet (68).
pub const STREAM_FRAMING_BYTES: usize = 2 * FRAMING_BYTES
    + dpsa_core::packets::STREAM_HEADER_PAYLOAD_LEN
    + dpsa_core::packets::END_PAYLOAD_LEN;

/// The MCU compressor: crate (pinned in Cargo.toml, so the label stays true).
pub const MCU_NAME: &str = "heatshrink-lib";
/// Its version.
pub const MCU_VERSION: &str = "1.0.0";
/// Window `2^MCU_W` bytes (the C library's default).
const MCU_W: usize = 8;
/// Back-reference length bits (the C library's default).
const MCU_L: usize = 4;
/// Decoder input buffer.
const MCU_I: usize = 32;
type McuEncoder = HeatshrinkEncoder<MCU_W, MCU_L, { 2 << MCU_W }>;
type McuDecoder = HeatshrinkDecoder<MCU_W, MCU_L, MCU_I, { 1 << MCU_W }>;

/// The rows under test: `rows x W` heights (0 where invalid) and packed validity
/// (`ceil(W/8)` bytes per row, bit `c % 8` of byte `c / 8`, padding bits 0).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BenchRows {
    /// Pixels per row `W`.
    pub width: usize,
    /// Rows held.
    pub rows: usize,
    heights: Vec<i16>,
    valid: Vec<u8>,
}

/// Pixels `codec-bench` takes at most (2^23 = 8.4 Mpx, half a paper-board camera's 7,900 x
/// 2,048): the whole-map methods (zstd, PNG) hold the map several times over, about 26 bytes
/// per pixel in all (measured: 217 MB peak for 8.4 Mpx). A larger input is refused as soon as
/// it passes the limit, before it is held.
pub const MAX_BENCH_PIXELS: usize = 1 << 23;

impl BenchRows {
    /// No rows yet, `w` pixels wide.
    fn empty(w: usize) -> Result<Self> {
        if w == 0 {
            return Err(SimError::refused("width 0: nothing to compress"));
        }
        if w > codec::MAX_WIDTH {
            return Err(SimError::Refused(format!(
                "width {w} exceeds the codec's {}",
                codec::MAX_WIDTH
            )));
        }
        Ok(BenchRows {
            width: w,
            rows: 0,
            heights: Vec::new(),
            valid: Vec::new(),
        })
    }

    /// Appends one row (invalid heights become 0); refuses a row of another width and more
    /// than [`MAX_BENCH_PIXELS`] in all.
    fn push(&mut self, row: &HeightRow) -> Result<()> {
        let w = self.width;
        if !(row.heights.len() == w && row.valid.len() == w) {
            return Err(SimError::Refused(format!(
                "board row {} has {} pixels, the map {w}",
                row.row,
                row.heights.len()
            )));
        }
        if (self.rows + 1) * w > MAX_BENCH_PIXELS {
            return Err(SimError::Refused(format!(
                "more than {} Mpx of heights: codec-bench takes at most {} Mpx (a shorter \
                 recording or stream)",
                MAX_BENCH_PIXELS >> 20,
                MAX_BENCH_PIXELS >> 20
            )));
        }
        let nb = w.div_ceil(8);
        let base = self.valid.len();
        self.valid.resize(base + nb, 0);
        for (c, (&h, &v)) in row.heights.iter().zip(&row.valid).enumerate() {
            self.heights.push(if v { h } else { 0 });
            if v {
                self.valid[base + c / 8] |= 1 << (c % 8);
            }
        }
        self.rows += 1;
        Ok(())
    }

    /// The rows of a decoded height map (all of them must have the map's width).
    pub fn from_map(map: &HeightMap) -> Result<Self> {
        if map.rows.is_empty() || map.width == 0 {
            return Err(SimError::refused("no decoded rows: nothing to compress"));
        }
        let mut rows = BenchRows::empty(map.width)?;
        for row in &map.rows {
            rows.push(row)?;
        }
        Ok(rows)
    }

    fn nb(&self) -> usize {
        self.width.div_ceil(8)
    }

    /// Heights and packed validity of row `r`.
    pub fn row(&self, r: usize) -> (&[i16], &[u8]) {
        let (w, nb) = (self.width, self.nb());
        (
            &self.heights[r * w..(r + 1) * w],
            &self.valid[r * nb..(r + 1) * nb],
        )
    }

    fn is_valid(&self, r: usize, c: usize) -> bool {
        self.valid[r * self.nb() + c / 8] >> (c % 8) & 1 != 0
    }

    /// Raw payload bytes of one row (codec 0).
    pub fn raw_row_bytes(&self) -> usize {
        codec::raw_len(self.width)
    }

    /// Raw bytes of all rows.
    pub fn raw_bytes(&self) -> usize {
        self.rows * self.raw_row_bytes()
    }

    /// Valid pixels over all rows.
    pub fn valid_pixels(&self) -> usize {
        self.valid.iter().map(|b| b.count_ones() as usize).sum()
    }

    /// Appends the raw payload of row `r`: validity bytes, then heights as i16 LE.
    fn push_raw(&self, r: usize, out: &mut Vec<u8>) {
        let (h, v) = self.row(r);
        out.extend_from_slice(v);
        for &x in h {
            out.extend_from_slice(&x.to_le_bytes());
        }
    }

    /// All raw payloads concatenated.
    fn raw_stream(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.raw_bytes());
        for r in 0..self.rows {
            self.push_raw(r, &mut out);
        }
        out
    }
}

/// Where the rows came from.
#[derive(Clone, Debug)]
pub enum Source {
    /// A recording, run through the fixed-point core.
    Recording,
    /// A packet stream file; `corrupt` packets were left out.
    Stream {
        /// Packets whose framing and CRC checked out.
        ok: usize,
        /// Damaged packets and stray bytes, counted and left out.
        corrupt: usize,
    },
}

/// Loads the rows: a directory is a recording (run through the fixed-point core), a file a
/// packet stream. Only rows that decoded are used.
pub fn load(path: &Path, progress: bool) -> Result<(BenchRows, Source)> {
    if path.is_dir() {
        let rec = Recording::open(path).at(|| format!("recording {}", path.display()))?;
        // Rows are taken as the core emits them; nothing else of the run is held.
        let mut rows = BenchRows::empty(rec.width())?;
        reconstruct::reconstruct_rows(&rec, progress, |row| rows.push(&row))?;
        if rows.rows == 0 {
            return Err(SimError::refused("no decoded rows: nothing to compress"));
        }
        Ok((rows, Source::Recording))
    } else {
        let file = crate::files::open_regular(path, "packet stream")?;
        // The LSB only labels the map; the codecs see LSB integers.
        let keep = stream::Keep {
            rows: true,
            max_pixels: MAX_BENCH_PIXELS as u64,
        };
        let d = stream::decode_reader_with(std::io::BufReader::new(file), 0.25, keep)
            .at(|| format!("reading {}", path.display()))?;
        if d.over_limit {
            return Err(SimError::Refused(format!(
                "packet stream {}: more than {} Mpx of heights, codec-bench takes at most {} Mpx",
                path.display(),
                MAX_BENCH_PIXELS >> 20,
                MAX_BENCH_PIXELS >> 20
            )));
        }
        let map = d.map.unwrap_or_default();
        let rows = BenchRows::from_map(&map).at(|| format!("packet stream {}", path.display()))?;
        Ok((
            rows,
            Source::Stream {
                ok: d.report.ok,
                corrupt: d.report.corrupt,
            },
        ))
    }
}

/// Compressed bytes per method.
#[derive(Clone, Debug, Serialize)]
pub struct Sizes {
    /// Row codec payloads, intra period 1 (every row decodable alone).
    pub ours: usize,
    /// `ours` plus the packet framing of every row and the stream's own packets.
    pub ours_framed: usize,
    /// Row codec payloads, intra period 32 (rows predicted from the previous row).
    pub ours_predicted: usize,
    /// `lz4_flex` block compression of each row's raw payload, summed over rows.
    pub lz4: usize,
    /// `lz4_flex` block compression of all raw payloads concatenated.
    pub lz4_stream: usize,
    /// heatshrink (the MCU compressor) on each row's raw payload, summed over rows.
    pub mcu: usize,
    /// zstd level 3 on all raw payloads concatenated.
    pub zstd3: usize,
    /// zstd level 19 on all raw payloads concatenated.
    pub zstd19: usize,
    /// The whole map as one 16-bit grey PNG.
    pub png16: usize,
}

/// Compression ratios (raw bytes / compressed bytes).
#[derive(Clone, Debug, Serialize)]
pub struct Ratios {
    /// Row codec, intra period 1, payloads only.
    pub ours: f64,
    /// Row codec with packet and stream framing (`compressed_bytes.ours_framed`).
    pub ours_framed: f64,
    /// Row codec, intra period 32.
    pub ours_predicted: f64,
    /// `lz4_flex`, row by row.
    pub lz4: f64,
    /// `lz4_flex`, all rows concatenated.
    pub lz4_stream: f64,
    /// heatshrink, row by row.
    pub mcu: f64,
    /// zstd level 3, all rows concatenated.
    pub zstd3: f64,
    /// zstd level 19, all rows concatenated.
    pub zstd19: f64,
    /// One 16-bit grey PNG of the whole map.
    pub png16: f64,
    /// `16 / H` (validity bits ignored; see the module docs).
    pub entropy_bound: f64,
    /// `ours` on the terms of `entropy_bound`: 16 bits per valid pixel over the bits of `ours`
    /// without its validity sections (headers and padding stay in).
    pub ours_heights_only: f64,
    /// `raw bits / (valid pixels x H)`: the bound on the raw size of the other ratios.
    pub entropy_bound_same_raw: f64,
}

/// Bits per valid pixel.
#[derive(Clone, Debug, Serialize)]
pub struct BitsPerPixel {
    /// Coded payload bits of `ours` (headers, validity and padding included) / valid pixels.
    pub ours: f64,
    /// Zeroth-order entropy `H` of the intra predictor's residuals at the valid pixels.
    pub entropy: f64,
    /// Entropy of the height noise alone: `log2(sigma sqrt(2 pi e))`.
    pub noise: f64,
    /// `ours / entropy`.
    pub ours_over_entropy: f64,
    /// `ours` by part (they add up to `ours`).
    pub ours_parts: OursParts,
}

/// Where the bits of `ours` go, bits per valid pixel.
#[derive(Clone, Debug, Serialize)]
pub struct OursParts {
    /// Rice codes of the valid pixels' residuals (compare with `entropy`).
    pub residuals: f64,
    /// Validity sections (runs of invalid pixels, or `W` plain bits).
    pub validity: f64,
    /// Payload headers (2 bytes per row) and padding to whole bytes.
    pub header_and_padding: f64,
    /// Rows sent raw.
    pub raw_rows: f64,
}

/// The height noise estimate (`noise` in the JSON).
#[derive(Clone, Debug, Serialize)]
pub struct Noise {
    /// Estimated height noise, LSB.
    pub sigma_lsb: f64,
    /// Second differences it was estimated from.
    pub samples: usize,
}

/// Host throughput in raw MB (10^6 bytes) per second, best of several passes.
#[derive(Clone, Debug, Serialize)]
pub struct Throughput {
    /// `ours` encoder.
    pub encode: f64,
    /// `ours` decoder (its output is checked against the input after the timed passes).
    pub decode: f64,
    /// `lz4_flex` block compression, row by row.
    pub lz4_encode: f64,
}

/// The largest `ours` row payload against the codec's bound (`worst_row_payload`).
#[derive(Clone, Debug, Serialize)]
pub struct WorstRow {
    /// Largest `ours` payload of a row, bytes.
    pub bytes: usize,
    /// `codec::max_len(W)`.
    pub max_len: usize,
    /// Rows the encoder had to send raw.
    pub raw_rows: usize,
}

/// The MCU compressor behind the `mcu` method (`mcu_compressor` in the JSON).
#[derive(Clone, Debug, Serialize)]
pub struct McuInfo {
    /// Crate name ([`MCU_NAME`]).
    pub name: &'static str,
    /// Crate version ([`MCU_VERSION`]).
    pub version: &'static str,
    /// Window, lookahead and search-index settings it ran with.
    pub config: String,
}

/// The benchmark result (`--json` prints it).
#[derive(Clone, Debug, Serialize)]
pub struct CodecReport {
    /// Rows compressed.
    pub rows: usize,
    /// Pixels per row `W`.
    pub width: usize,
    /// Raw payload bytes of all rows (codec 0): the numerator of every ratio.
    pub raw_bytes: usize,
    /// Valid pixels over all rows.
    pub valid_pixels: usize,
    /// Which MCU compressor `mcu` ran.
    pub mcu_compressor: McuInfo,
    /// Compression ratio per method.
    pub ratio: Ratios,
    /// Compressed size per method, bytes.
    pub compressed_bytes: Sizes,
    /// Bits per valid pixel of `ours`, of the residual entropy and of the noise.
    pub bits_per_pixel: BitsPerPixel,
    /// The height noise estimate behind `bits_per_pixel.noise`.
    pub noise: Noise,
    /// Host throughput, raw MB (10^6 bytes) per second.
    pub host_mb_s: Throughput,
    /// The largest `ours` row payload.
    pub worst_row_payload: WorstRow,
}

impl CodecReport {
    /// Best ratio among the general-purpose compressors (lz4, lz4_stream, mcu, zstd, PNG).
    pub fn best_general_purpose(&self) -> (&'static str, f64) {
        let r = &self.ratio;
        [
            ("lz4", r.lz4),
            ("lz4_stream", r.lz4_stream),
            ("mcu", r.mcu),
            ("zstd3", r.zstd3),
            ("zstd19", r.zstd19),
            ("png16", r.png16),
        ]
        .into_iter()
        .fold(("none", 0.0), |best, x| if x.1 > best.1 { x } else { best })
    }

    /// The readable table.
    pub fn table(&self) -> String {
        use std::fmt::Write;
        let px = self.rows * self.width;
        let raw_bpp = self.raw_bytes as f64 * 8.0 / px as f64;
        let mut s = String::new();
        let _ = writeln!(
            s,
            "codec-bench: {} rows x {} px, {:.1} % valid; raw {} bytes ({raw_bpp:.2} bits/px: i16 height + validity bit)",
            self.rows,
            self.width,
            100.0 * self.valid_pixels as f64 / px as f64,
            self.raw_bytes
        );
        let _ = writeln!(s);
        let _ = writeln!(s, "{:<16} {:>12} {:>8}  note", "method", "bytes", "ratio");
        let (b, r) = (&self.compressed_bytes, &self.ratio);
        let mcu = format!(
            "{} {} ({}), row by row, no allocation",
            self.mcu_compressor.name, self.mcu_compressor.version, self.mcu_compressor.config
        );
        let lines: [(&str, usize, f64, &str); 9] = [
            (
                "ours",
                b.ours,
                r.ours,
                "row codec, intra period 1 (every row decodable alone), payloads",
            ),
            (
                "ours_framed",
                b.ours_framed,
                r.ours_framed,
                "the same + 36 bytes of packet framing per row",
            ),
            (
                "ours_predicted",
                b.ours_predicted,
                r.ours_predicted,
                "row codec, intra period 32 (rows predicted from the previous one)",
            ),
            ("lz4", b.lz4, r.lz4, "lz4_flex block, row by row"),
            (
                "lz4_stream",
                b.lz4_stream,
                r.lz4_stream,
                "lz4_flex block, all rows concatenated",
            ),
            ("mcu", b.mcu, r.mcu, &mcu),
            (
                "zstd3",
                b.zstd3,
                r.zstd3,
                "zstd level 3, all rows concatenated",
            ),
            (
                "zstd19",
                b.zstd19,
                r.zstd19,
                "zstd level 19, all rows concatenated",
            ),
            (
                "png16",
                b.png16,
                r.png16,
                "one 16-bit grey PNG, best compression, adaptive filter",
            ),
        ];
        for (name, bytes, ratio, note) in lines {
            let _ = writeln!(s, "{name:<16} {bytes:>12} {ratio:>8.3}  {note}");
        }
        let _ = writeln!(
            s,
            "{:<16} {:>12} {:>8.3}  16 / H: 16 bits per valid pixel, validity bits ignored",
            "entropy_bound", "-", r.entropy_bound
        );
        let _ = writeln!(
            s,
            "{:<16} {:>12} {:>8.3}  raw bits / (valid px x H): same raw size as the ratios above",
            "  (same raw)", "-", r.entropy_bound_same_raw
        );
        let _ = writeln!(s);
        let bp = &self.bits_per_pixel;
        let _ = writeln!(
            s,
            "bits per valid pixel: ours {:.3}, residual entropy H {:.3} (ours / H = {:.3}), noise {:.3} (sigma {:.2} LSB from {} second differences)",
            bp.ours, bp.entropy, bp.ours_over_entropy, bp.noise, self.noise.sigma_lsb, self.noise.samples
        );
        let p = &bp.ours_parts;
        let _ = writeln!(
            s,
            "ours = residual codes {:.3} + validity {:.3} + headers and padding {:.3} + raw rows {:.3} bits per valid pixel; \
             without the validity bits {:.3} : 1, {:.1} % of entropy_bound",
            p.residuals,
            p.validity,
            p.header_and_padding,
            p.raw_rows,
            r.ours_heights_only,
            100.0 * r.ours_heights_only / r.entropy_bound
        );
        let (best, best_ratio) = self.best_general_purpose();
        let _ = writeln!(
            s,
            "ours vs best general-purpose ({best} {best_ratio:.3}): {:+.1} %",
            (r.ours / best_ratio - 1.0) * 100.0
        );
        let wr = &self.worst_row_payload;
        let _ = writeln!(
            s,
            "worst row payload: {} bytes of max_len({}) = {} ({} rows sent raw)",
            wr.bytes, self.width, wr.max_len, wr.raw_rows
        );
        let t = &self.host_mb_s;
        let _ = write!(
            s,
            "host throughput, raw MB/s: ours encode {:.1}, ours decode {:.1} (every row round-trips exactly), lz4 encode {:.1}",
            t.encode, t.decode, t.lz4_encode
        );
        s
    }
}

/// Stage bar: created (and drawn) only once the run has taken a second, or at once when
/// `now` (a run that will clearly take longer).
struct Stages {
    shared: Arc<Mutex<BarState>>,
    done: Option<mpsc::Sender<()>>,
    watcher: Option<std::thread::JoinHandle<()>>,
}

#[derive(Default)]
struct BarState {
    pos: u64,
    what: String,
    bar: Option<ProgressBar>,
}

impl BarState {
    fn show(&mut self, stages: u64) {
        let bar = progress_bar(true, stages, &self.what);
        bar.set_position(self.pos);
        bar.enable_steady_tick(Duration::from_millis(200));
        self.bar = Some(bar);
    }
}

impl Stages {
    fn new(progress: bool, stages: u64, now: bool) -> Self {
        let shared = Arc::new(Mutex::new(BarState {
            what: "codec-bench".into(),
            ..BarState::default()
        }));
        if !progress {
            return Stages {
                shared,
                done: None,
                watcher: None,
            };
        }
        if now {
            lock(&shared).show(stages);
            return Stages {
                shared,
                done: None,
                watcher: None,
            };
        }
        let (tx, rx) = mpsc::channel::<()>();
        let state = Arc::clone(&shared);
        let watcher = std::thread::spawn(move || {
            if let Err(mpsc::RecvTimeoutError::Timeout) = rx.recv_timeout(Duration::from_secs(1)) {
                lock(&state).show(stages);
            }
        });
        Stages {
            shared,
            done: Some(tx),
            watcher: Some(watcher),
        }
    }

    fn start(&self, what: &str) {
        let mut s = lock(&self.shared);
        s.what = what.to_string();
        if let Some(bar) = &s.bar {
            bar.set_prefix(what.to_string());
        }
    }

    fn next(&self) {
        let mut s = lock(&self.shared);
        s.pos += 1;
        if let Some(bar) = &s.bar {
            bar.inc(1);
        }
    }
}

fn lock(m: &Mutex<BarState>) -> std::sync::MutexGuard<'_, BarState> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Drop for Stages {
    fn drop(&mut self) {
        drop(self.done.take());
        if let Some(w) = self.watcher.take() {
            let _ = w.join();
        }
        if let Some(bar) = lock(&self.shared).bar.take() {
            bar.finish_and_clear();
        }
    }
}

/// Best wall time of `f` over at least 3 passes and about 0.3 s.
fn best_time(mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    let start = Instant::now();
    let mut best = f64::INFINITY;
    let mut n = 0;
    while n < 3 || (n < 50 && start.elapsed() < Duration::from_millis(300)) {
        let t = Instant::now();
        f()?;
        best = best.min(t.elapsed().as_secs_f64());
        n += 1;
    }
    Ok(best.max(1e-9))
}

/// `ours` at intra period `intra_period`: payloads (stride `max_len`), their lengths, and the best
/// encode and decode times. Fails if a decoded row differs from the input.
struct Coded {
    lens: Vec<usize>,
    encode_s: f64,
    decode_s: f64,
}

fn run_ours(rows: &BenchRows, intra_period: u32) -> Result<Coded> {
    let (w, nb, n) = (rows.width, rows.nb(), rows.rows);
    let stride = codec::max_len(w);
    let mut buf = vec![0u8; n * stride];
    let mut lens = vec![0usize; n];
    let (mut eh, mut ev) = (vec![0i16; w], vec![0u8; nb]);
    let mut enc = Encoder::new(&mut eh, &mut ev, w, intra_period)
        .ok_or_else(|| SimError::Core("codec encoder".into()))?;
    let encode_s = best_time(|| {
        enc.reset();
        for (r, (out, len)) in buf.chunks_exact_mut(stride).zip(&mut lens).enumerate() {
            let (h, v) = rows.row(r);
            *len = enc
                .encode(h, v, out)
                .map_err(|e| SimError::Core(format!("codec encode row {r}: {e}")))?;
        }
        Ok(())
    })?;
    let (mut dh, mut dv) = (vec![0i16; w], vec![0u8; nb]);
    let mut dec =
        Decoder::new(&mut dh, &mut dv, w).ok_or_else(|| SimError::Core("codec decoder".into()))?;
    let (mut oh, mut ov) = (vec![0i16; n * w], vec![0u8; n * nb]);
    let decode_s = best_time(|| {
        dec.reset();
        for (r, ((p, h), v)) in buf
            .chunks_exact(stride)
            .zip(oh.chunks_exact_mut(w))
            .zip(ov.chunks_exact_mut(nb))
            .enumerate()
        {
            dec.decode(&p[..lens[r]], h, v)
                .map_err(|e| SimError::Core(format!("codec decode row {r}: {e}")))?;
        }
        Ok(())
    })?;
    for r in 0..n {
        let (h, v) = rows.row(r);
        if oh[r * w..(r + 1) * w] != *h || ov[r * nb..(r + 1) * nb] != *v {
            return Err(SimError::RoundTrip(format!(
                "row codec (intra period {intra_period}): row {r} does not round-trip"
            )));
        }
    }
    Ok(Coded {
        lens,
        encode_s,
        decode_s,
    })
}

/// What the codec spends on one intra row, by the model of [`intra_row`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RowBits {
    /// Payload bytes (header included); the encoder must produce exactly this many.
    pub len: usize,
    /// Bits of the validity section (0 for a raw row).
    pub validity: usize,
    /// Bits of the Rice codes of the valid pixels (0 for a raw row).
    pub residuals: usize,
    /// The row is sent raw (its coded body would be longer than the raw body).
    pub raw: bool,
}

/// Intra-row model of the codec (module docs of `codec`): adds the residual of every valid
/// pixel to `hist` (index: residual as u16) and returns what the encoder must spend on this
/// row as an intra row.
pub fn intra_row(heights: &[i16], valid: &[u8], width: usize, hist: &mut [u64]) -> RowBits {
    let w = width;
    let bit = |c: usize| valid[c / 8] >> (c % 8) & 1 != 0;
    // Validity section: runs of m = !valid starting with a run of 0s (valid pixels).
    let gamma = |v: usize| 2 * (usize::BITS - v.leading_zeros()) as usize - 1;
    let mut mask_bits = 0;
    let mut c = 0;
    let mut value = true; // valid, i.e. m = 0
    while c < w {
        let s = c;
        while c < w && bit(c) == value {
            c += 1;
        }
        mask_bits += gamma(c - s + usize::from(s == 0));
        value = !value;
    }
    let mask_bits = if mask_bits > w { w } else { mask_bits };
    // Pixels: filled row R, 2-neighbour predictor, adaptive Rice per context.
    let mut acc = [448u32; 3];
    let (mut a, mut aa) = (0i32, 0i32); // R[c-1], R[c-2]
    let mut px_bits = 0usize;
    for (c, &x) in heights.iter().enumerate().take(w) {
        let r = if bit(c) {
            let g = (a - aa).abs();
            let (pred, t) = if g < 48 {
                ((a + aa + 1) >> 1, usize::from(g >= 16))
            } else {
                (a, 2)
            };
            let e = (i32::from(x) - pred) as i16;
            hist[e as u16 as usize] += 1;
            let z = u32::from(((e << 1) ^ (e >> 15)) as u16);
            let k = 32 - (acc[t] >> 6).leading_zeros();
            px_bits += if z >> k < 16 {
                ((z >> k) + 1 + k) as usize
            } else {
                32
            };
            acc[t] = acc[t] - (acc[t] >> 5) + z;
            i32::from(x)
        } else {
            a
        };
        (aa, a) = (a, r);
    }
    let body = (mask_bits + px_bits).div_ceil(8);
    if body > codec::raw_len(w) {
        // A coded body longer than the raw body is sent raw.
        RowBits {
            len: codec::max_len(w),
            validity: 0,
            residuals: 0,
            raw: true,
        }
    } else {
        RowBits {
            len: codec::HEADER_LEN + body,
            validity: mask_bits,
            residuals: px_bits,
            raw: false,
        }
    }
}

/// Zeroth-order entropy of a histogram, bits per sample.
fn entropy(hist: &[u64]) -> f64 {
    let n: u64 = hist.iter().sum();
    if n == 0 {
        return 0.0;
    }
    let n = n as f64;
    hist.iter()
        .filter(|&&k| k > 0)
        .map(|&k| -(k as f64 / n) * (k as f64 / n).log2())
        .sum()
}

/// Height noise (LSB) from the horizontal second differences of valid pixel triples:
/// `1.4826 MAD / sqrt(6)`; also the number of differences.
pub fn noise_sigma(rows: &BenchRows) -> (f64, usize) {
    let w = rows.width;
    let mut d: Vec<u32> = Vec::new();
    for r in 0..rows.rows {
        let (h, _) = rows.row(r);
        for c in 1..w.saturating_sub(1) {
            if rows.is_valid(r, c - 1) && rows.is_valid(r, c) && rows.is_valid(r, c + 1) {
                let d2 = i32::from(h[c - 1]) - 2 * i32::from(h[c]) + i32::from(h[c + 1]);
                d.push(d2.unsigned_abs());
            }
        }
    }
    let n = d.len();
    if n == 0 {
        return (0.0, 0);
    }
    let half = n as f64 / 2.0;
    let m = *d.select_nth_unstable(n / 2).1;
    let below = d.iter().filter(|&&x| x < m).count() as f64;
    let at = d.iter().filter(|&&x| x == m).count() as f64;
    // |d| = m stands for the continuous interval [m - 1/2, m + 1/2) ([0, 1/2) for m = 0).
    let (lo, width) = if m == 0 {
        (0.0, 0.5)
    } else {
        (f64::from(m) - 0.5, 1.0)
    };
    let mad = lo + width * ((half - below) / at).clamp(0.0, 1.0);
    (1.482_6 * mad / 6f64.sqrt(), n)
}

/// Entropy of a Gaussian of `sigma` LSB quantised to integers (`sigma >~ 1`), bits; 0 below.
pub fn gaussian_bits(sigma: f64) -> f64 {
    (sigma * (2.0 * std::f64::consts::PI * std::f64::consts::E).sqrt())
        .log2()
        .max(0.0)
}

fn mcu_compress(enc: &mut McuEncoder, src: &[u8], dst: &mut [u8]) -> Result<usize> {
    enc.reset();
    let (mut i, mut o) = (0, 0);
    loop {
        if i < src.len() {
            match enc.sink(&src[i..]) {
                Ok(k) => i += k,
                Err(SinkError::Full) => {}
                Err(e) => return Err(SimError::RoundTrip(format!("heatshrink encoder: {e:?}"))),
            }
        }
        if i == src.len() {
            enc.finish();
        }
        if o >= dst.len() {
            return Err(SimError::RoundTrip(format!(
                "heatshrink output exceeds {} bytes",
                dst.len()
            )));
        }
        match enc.poll(&mut dst[o..]) {
            Ok(Poll::More(k)) => o += k,
            Ok(Poll::Empty(k)) => {
                o += k;
                if i == src.len() {
                    return Ok(o);
                }
            }
            Err(e) => return Err(SimError::RoundTrip(format!("heatshrink encoder: {e:?}"))),
        }
    }
}

fn mcu_decompress(dec: &mut McuDecoder, src: &[u8], dst: &mut [u8]) -> Result<usize> {
    dec.reset();
    let (mut i, mut o) = (0, 0);
    let mut spare = [0u8; 16];
    for _ in 0..10 * (src.len() + dst.len()) + 100 {
        if i < src.len() {
            match dec.sink(&src[i..]) {
                Ok(k) => i += k,
                Err(SinkError::Full) => {}
                Err(e) => return Err(SimError::RoundTrip(format!("heatshrink decoder: {e:?}"))),
            }
        }
        let full = o == dst.len();
        let out = if full { &mut spare[..] } else { &mut dst[o..] };
        let (k, empty) = match dec.poll(out) {
            Ok(Poll::More(k)) => (k, false),
            Ok(Poll::Empty(k)) => (k, true),
            Err(e) => return Err(SimError::RoundTrip(format!("heatshrink decoder: {e:?}"))),
        };
        if full && k > 0 {
            return Err(SimError::RoundTrip(format!(
                "heatshrink decoded more than {} bytes",
                dst.len()
            )));
        }
        o += k;
        if empty && i == src.len() {
            return Ok(o);
        }
    }
    Err(SimError::RoundTrip(
        "heatshrink decoder does not finish".into(),
    ))
}

/// The 16-bit PNG of the map: `h + 32768` where valid (at least 1), 0 where invalid.
fn png_pixels(rows: &BenchRows) -> Vec<u16> {
    let w = rows.width;
    (0..rows.rows * w)
        .map(|i| {
            let (r, c) = (i / w, i % w);
            if rows.is_valid(r, c) {
                (i32::from(rows.heights[i]) + 32768).max(1) as u16
            } else {
                0
            }
        })
        .collect()
}

fn png16(rows: &BenchRows) -> Result<usize> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::{ExtendedColorType, ImageEncoder};
    let px = png_pixels(rows);
    let bytes: Vec<u8> = px.iter().flat_map(|v| v.to_ne_bytes()).collect();
    let mut png = Vec::new();
    PngEncoder::new_with_quality(&mut png, CompressionType::Best, FilterType::Adaptive)
        .write_image(
            &bytes,
            rows.width as u32,
            rows.rows as u32,
            ExtendedColorType::L16,
        )
        .map_err(|e| SimError::RoundTrip(chain(&e)))
        .at(|| "PNG encoding")?;
    let back = image::load_from_memory_with_format(&png, image::ImageFormat::Png)
        .map_err(|e| SimError::RoundTrip(chain(&e)))
        .at(|| "PNG decoding")?
        .into_luma16();
    if back.as_raw() != &px {
        return Err(SimError::RoundTrip("PNG does not round-trip".into()));
    }
    Ok(png.len())
}

const STAGES: u64 = 9;

/// Runs every method on `rows`.
pub fn run(rows: &BenchRows, progress: bool) -> Result<CodecReport> {
    let (w, n) = (rows.width, rows.rows);
    let raw = rows.raw_bytes();
    let valid_px = rows.valid_pixels();
    if valid_px == 0 {
        return Err(SimError::refused("no valid pixels: nothing to benchmark"));
    }
    // Show the bar at once when the run will clearly take over a second (zstd -19 alone runs
    // at a few MB/s), else only once a second has passed.
    let stages = Stages::new(progress, STAGES, raw > 4_000_000);
    let mb = raw as f64 / 1e6;

    stages.start("ours");
    let ours = run_ours(rows, 1)?;
    let ours_bytes: usize = ours.lens.iter().sum();
    let worst = ours.lens.iter().copied().max().unwrap_or(0);
    stages.next();

    stages.start("predicted");
    let pred = run_ours(rows, dpsa_core::packets::PREDICTED_INTRA_PERIOD)?;
    let pred_bytes: usize = pred.lens.iter().sum();
    stages.next();

    stages.start("entropy");
    let mut hist = vec![0u64; 1 << 16];
    let (mut raw_rows, mut raw_row_bits, mut validity_bits, mut residual_bits) = (0, 0, 0, 0);
    for r in 0..n {
        let (h, v) = rows.row(r);
        let model = intra_row(h, v, w, &mut hist);
        if model.len != ours.lens[r] {
            return Err(SimError::Internal(format!(
                "the reproduced intra predictor and Rice model give {} bytes for row {r}, the codec {}",
                model.len,
                ours.lens[r]
            )));
        }
        raw_rows += usize::from(model.raw);
        raw_row_bits += if model.raw { model.len * 8 } else { 0 };
        validity_bits += model.validity;
        residual_bits += model.residuals;
    }
    let h_bits = entropy(&hist);
    let (sigma, samples) = noise_sigma(rows);
    stages.next();

    stages.start("lz4");
    let stride = lz4_flex::block::get_maximum_output_size(rows.raw_row_bytes());
    let raw_rows_bytes: Vec<Vec<u8>> = (0..n)
        .map(|r| {
            let mut v = Vec::with_capacity(rows.raw_row_bytes());
            rows.push_raw(r, &mut v);
            v
        })
        .collect();
    let mut lz = vec![0u8; n * stride];
    let mut lz_lens = vec![0usize; n];
    let lz4_s = best_time(|| {
        for ((src, out), len) in raw_rows_bytes
            .iter()
            .zip(lz.chunks_exact_mut(stride))
            .zip(&mut lz_lens)
        {
            *len = lz4_flex::block::compress_into(src, out)
                .map_err(|e| SimError::RoundTrip(chain(&e)))
                .at(|| "lz4 compress")?;
        }
        Ok(())
    })?;
    let mut back = vec![0u8; rows.raw_row_bytes()];
    for (r, src) in raw_rows_bytes.iter().enumerate() {
        let k =
            lz4_flex::block::decompress_into(&lz[r * stride..r * stride + lz_lens[r]], &mut back)
                .map_err(|e| SimError::RoundTrip(chain(&e)))
                .at(|| "lz4 decompress")?;
        if !(k == back.len() && back == *src) {
            return Err(SimError::RoundTrip(format!(
                "lz4: row {r} does not round-trip"
            )));
        }
    }
    let lz4_bytes: usize = lz_lens.iter().sum();
    stages.next();

    stages.start("lz4 stream");
    let stream = rows.raw_stream();
    let lzs = lz4_flex::block::compress(&stream);
    let lz_back = lz4_flex::block::decompress(&lzs, stream.len())
        .map_err(|e| SimError::RoundTrip(chain(&e)))
        .at(|| "lz4 decompress")?;
    if lz_back != stream {
        return Err(SimError::RoundTrip("lz4 stream does not round-trip".into()));
    }
    stages.next();

    stages.start("heatshrink");
    let mut enc = McuEncoder::new();
    let mut dec = McuDecoder::new();
    let mut hs = vec![0u8; rows.raw_row_bytes() * 9 / 8 + 64];
    let mut mcu_bytes = 0;
    for (r, src) in raw_rows_bytes.iter().enumerate() {
        let k = mcu_compress(&mut enc, src, &mut hs)?;
        let m = mcu_decompress(&mut dec, &hs[..k], &mut back)?;
        if !(m == back.len() && back == *src) {
            return Err(SimError::RoundTrip(format!(
                "heatshrink: row {r} does not round-trip"
            )));
        }
        mcu_bytes += k;
    }
    stages.next();

    let mut zstd_bytes = [0usize; 2];
    for (i, level) in [3, 19].into_iter().enumerate() {
        stages.start(if level == 3 { "zstd -3" } else { "zstd -19" });
        let z = zstd::bulk::compress(&stream, level).at(|| "zstd compress")?;
        if zstd::bulk::decompress(&z, stream.len()).at(|| "zstd decompress")? != stream {
            return Err(SimError::RoundTrip(format!(
                "zstd -{level} does not round-trip"
            )));
        }
        zstd_bytes[i] = z.len();
        stages.next();
    }

    stages.start("png");
    let png_bytes = png16(rows)?;
    stages.next();
    drop(stages);

    let ratio = |b: usize| raw as f64 / b as f64;
    let per_px = |bits: usize| bits as f64 / valid_px as f64;
    let ours_bpp = per_px(ours_bytes * 8);
    Ok(CodecReport {
        rows: n,
        width: w,
        raw_bytes: raw,
        valid_pixels: valid_px,
        mcu_compressor: McuInfo {
            name: MCU_NAME,
            version: MCU_VERSION,
            config: format!("window 2^{MCU_W}, lookahead 2^{MCU_L}, with search index"),
        },
        ratio: Ratios {
            ours: ratio(ours_bytes),
            ours_framed: ratio(ours_bytes + n * FRAMING_BYTES + STREAM_FRAMING_BYTES),
            ours_predicted: ratio(pred_bytes),
            lz4: ratio(lz4_bytes),
            lz4_stream: ratio(lzs.len()),
            mcu: ratio(mcu_bytes),
            zstd3: ratio(zstd_bytes[0]),
            zstd19: ratio(zstd_bytes[1]),
            png16: ratio(png_bytes),
            entropy_bound: 16.0 / h_bits,
            ours_heights_only: 16.0 * valid_px as f64 / (ours_bytes * 8 - validity_bits) as f64,
            entropy_bound_same_raw: raw as f64 * 8.0 / (valid_px as f64 * h_bits),
        },
        compressed_bytes: Sizes {
            ours: ours_bytes,
            ours_framed: ours_bytes + n * FRAMING_BYTES + STREAM_FRAMING_BYTES,
            ours_predicted: pred_bytes,
            lz4: lz4_bytes,
            lz4_stream: lzs.len(),
            mcu: mcu_bytes,
            zstd3: zstd_bytes[0],
            zstd19: zstd_bytes[1],
            png16: png_bytes,
        },
        bits_per_pixel: BitsPerPixel {
            ours: ours_bpp,
            entropy: h_bits,
            noise: gaussian_bits(sigma),
            ours_over_entropy: ours_bpp / h_bits,
            ours_parts: OursParts {
                residuals: per_px(residual_bits),
                validity: per_px(validity_bits),
                header_and_padding: per_px(
                    ours_bytes * 8 - residual_bits - validity_bits - raw_row_bits,
                ),
                raw_rows: per_px(raw_row_bits),
            },
        },
        noise: Noise {
            sigma_lsb: sigma,
            samples,
        },
        host_mb_s: Throughput {
            encode: mb / ours.encode_s,
            decode: mb / ours.decode_s,
            lz4_encode: mb / lz4_s,
        },
        worst_row_payload: WorstRow {
            bytes: worst,
            max_len: codec::max_len(w),
            raw_rows,
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::heightmap::HeightRow;

    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }
        fn unit(&mut self) -> f64 {
            ((self.next() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        }
        fn gauss(&mut self) -> f64 {
            (-2.0 * self.unit().ln()).sqrt() * (std::f64::consts::TAU * self.unit()).cos()
        }
    }

    fn map(w: usize, rows: Vec<(Vec<i16>, Vec<bool>)>) -> HeightMap {
        let mut m = HeightMap::new(w, 0.25);
        for (i, (heights, valid)) in rows.into_iter().enumerate() {
            m.rows.push(HeightRow {
                row: i as i64,
                latch: 0,
                flags: 0,
                heights,
                valid,
            });
        }
        m
    }

    /// Rows of many kinds: noisy board with deposits, validity runs, alternating validity
    /// (plain mask), random i16, nothing valid, extreme values, residuals of -32768 (raw).
    fn kinds(rng: &mut Rng, w: usize) -> Vec<(Vec<i16>, Vec<bool>)> {
        let mut out = Vec::new();
        for kind in 0..8 {
            let heights: Vec<i16> = (0..w)
                .map(|c| match kind {
                    3 => rng.next() as i16,
                    6 => [i16::MIN, i16::MAX, 0, -1][(rng.next() % 4) as usize],
                    7 => [0, i16::MIN][c % 2],
                    _ => {
                        let dep = if (c / 37) % 3 == 0 { 600.0 } else { 0.0 };
                        (8.0 * rng.gauss() + dep + c as f64 * 0.1).round() as i16
                    }
                })
                .collect();
            let valid: Vec<bool> = (0..w)
                .map(|c| match kind {
                    1 => (c / 11) % 4 != 0,
                    2 => c % 2 == 0,
                    4 => false,
                    5 => rng.next() % 10 != 0,
                    _ => true,
                })
                .collect();
            out.push((heights, valid));
        }
        out
    }

    #[test]
    fn intra_model_matches_the_encoder() {
        let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
        for w in [1usize, 2, 7, 9, 64, 256, 1000, 2048] {
            let rows = BenchRows::from_map(&map(w, kinds(&mut rng, w))).unwrap();
            let coded = run_ours(&rows, 1).unwrap();
            let mut hist = vec![0u64; 1 << 16];
            for r in 0..rows.rows {
                let (h, v) = rows.row(r);
                let m = intra_row(h, v, w, &mut hist);
                assert_eq!(m.len, coded.lens[r], "w {w} row {r}");
                if !m.raw {
                    assert_eq!(
                        codec::HEADER_LEN + (m.validity + m.residuals).div_ceil(8),
                        m.len
                    );
                }
            }
            assert_eq!(hist.iter().sum::<u64>() as usize, rows.valid_pixels());
            if w >= 64 {
                // Residuals of -32768 (escapes, 32 bits per pixel) go raw.
                let (h, v) = rows.row(7);
                assert!(intra_row(h, v, w, &mut hist).raw, "w {w}");
            }
        }
    }

    #[test]
    fn rows_zero_invalid_heights_and_pack_validity() {
        let m = map(
            10,
            vec![(
                vec![5, 6, 7, 8, 9, 10, 11, 12, 13, 14],
                (0..10).map(|c| c != 2 && c != 9).collect(),
            )],
        );
        let rows = BenchRows::from_map(&m).unwrap();
        let (h, v) = rows.row(0);
        assert_eq!(h, [5, 6, 0, 8, 9, 10, 11, 12, 13, 0]);
        assert_eq!(v, [0b1111_1011, 0b0000_0001]);
        assert_eq!(rows.raw_bytes(), 2 + 20);
        assert_eq!(rows.valid_pixels(), 8);
        let mut raw = Vec::new();
        rows.push_raw(0, &mut raw);
        assert_eq!(raw.len(), rows.raw_row_bytes());
        assert_eq!(&raw[..4], [0b1111_1011, 0b0000_0001, 5, 0]);
        assert!(BenchRows::from_map(&HeightMap::new(10, 0.25)).is_err());
    }

    #[test]
    fn noise_estimate_is_robust_to_slopes_and_steps() {
        let mut rng = Rng(77);
        for sigma in [2.0, 8.0, 20.0] {
            let w = 1024;
            let rows: Vec<_> = (0..200)
                .map(|r| {
                    let h = (0..w)
                        .map(|c| {
                            let step = if (c + 13 * r) % 300 < 90 { 700.0 } else { 0.0 };
                            (sigma * rng.gauss() + 0.3 * c as f64 + step).round() as i16
                        })
                        .collect();
                    (h, vec![true; w])
                })
                .collect();
            let (est, n) = noise_sigma(&BenchRows::from_map(&map(w, rows)).unwrap());
            assert_eq!(n, 200 * (w - 2));
            // Rounding to integers adds 1/12 LSB^2 of variance.
            let expect = (sigma * sigma + 1.0 / 12.0f64).sqrt();
            assert!(
                (est / expect - 1.0).abs() < 0.03,
                "sigma {sigma}: estimated {est}"
            );
        }
        assert!((gaussian_bits(8.0) - 5.047).abs() < 1e-3);
    }

    #[test]
    fn heatshrink_round_trips() {
        let mut rng = Rng(5);
        let mut enc = McuEncoder::new();
        let mut dec = McuDecoder::new();
        for len in [1usize, 2, 31, 511, 512, 513, 4352] {
            for kind in 0..3 {
                let src: Vec<u8> = (0..len)
                    .map(|i| match kind {
                        0 => 0,
                        1 => (i % 7) as u8,
                        _ => rng.next() as u8,
                    })
                    .collect();
                let mut packed = vec![0u8; len * 9 / 8 + 64];
                let k = mcu_compress(&mut enc, &src, &mut packed).unwrap();
                let mut back = vec![0u8; len];
                assert_eq!(
                    mcu_decompress(&mut dec, &packed[..k], &mut back).unwrap(),
                    len
                );
                assert_eq!(back, src, "len {len} kind {kind}");
            }
        }
    }
}
