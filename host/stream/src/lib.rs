//! Packet streams: decoding a stream of packets back into a height map, with the damage report
//! (good and corrupt packets, resynchronisations) and, for version 2 streams, what the stream
//! says about itself: its header, gap records, missing / duplicated / reordered packets and
//! whether it ended (`dpsa_core::packets::Tracker`).
//!
//! The input is read in chunks ([`decode_reader`]): memory is the chunk buffer, the decoded rows
//! and at most [`MAX_DAMAGE_ENTRIES`] damage entries and [`MAX_GAP_ENTRIES`] gap entries (the
//! counts are always complete); time is linear in the input (`dpsa_core::packets::Walk`).
//!
//! [`config`]: the core's configuration of a camera (from a recording's manifest or a
//! calibration file), whose hash every stream header carries.

pub mod config;

use dpsa_core::packets::{
    self, codec, Item, Kind, Packet, PacketError, Summary, Totals, Tracker, Verdict, Walk,
    MAX_PACKET_LEN,
};
use dpsa_core::Trigger;
use dpsa_formats::heightmap::{HeightMap, HeightRow};
use serde::Serialize;
use std::io::Read;

/// Damage entries kept in a report (the counts go on).
pub const MAX_DAMAGE_ENTRIES: usize = 100;
/// Gap records kept in a report (the counts go on).
pub const MAX_GAP_ENTRIES: usize = 100;
/// Bytes read at a time.
const CHUNK: usize = 1 << 16;

/// A packet that could not be decoded, and where.
#[derive(Clone, Debug, Serialize)]
pub struct Damage {
    /// Byte offset of the damaged packet (or of the garbage) in the stream.
    pub offset: usize,
    /// What was wrong with it, one sentence.
    pub error: String,
}

/// A gap record: board rows `first .. first + count` never imaged (encoder fault).
#[derive(Clone, Copy, Debug, Serialize)]
pub struct GapEntry {
    /// First board row of the gap.
    pub first: i64,
    /// Board rows in the gap (at least 1).
    pub count: u64,
    /// Row flags of every row in the gap (`dpsa_formats::heightmap::flags`).
    pub flags: u16,
}

/// What a version 2 stream said about itself, and what the decoder found.
#[derive(Clone, Debug, Default, Serialize)]
pub struct StreamReport {
    /// Format version of the first packet (0: none).
    pub version: u8,
    /// Camera id from the stream header (`None`: no header arrived, e.g. version 1).
    pub camera: Option<u8>,
    /// Columns per row from the stream header, px (`None`: no header).
    pub width: Option<u16>,
    /// Run identity from the stream header (`None`: no header; 0: the producer gave none).
    pub run_id: Option<u64>,
    /// The configuration's hash from the stream header as 16 lowercase hex digits (`None`:
    /// no header).
    pub config_hash: Option<String>,
    /// Codec intra period from the stream header, rows (`None`: no header).
    pub intra_period: Option<u32>,
    /// Observations per row `n` from the stream header (`None`: no header).
    pub n: Option<u8>,
    /// ROI rows per frame `H` from the stream header (`None`: no header).
    pub frame_rows: Option<u16>,
    /// Rows a frame admits at most, from the stream header (`None`: no header).
    pub max_step_rows: Option<u16>,
    /// Packets lost (sequence numbers never seen, and packets the end's total says exist).
    pub missing: u64,
    /// Packets whose sequence number was seen already (version 1, which has none: board rows
    /// that arrived more than once).
    pub duplicated: u64,
    /// Packets that arrived after a packet with a higher sequence number.
    pub reordered: u64,
    /// Rows or gaps that arrived below a board row already seen.
    pub row_order: u64,
    /// Packets of another width than the stream's (not used).
    pub wrong_width: u64,
    /// Packets of another camera than the stream header's (not used: a stream carries one
    /// camera, so these are another camera's packets spliced in).
    pub other_camera: u64,
    /// Packets after the end packet.
    pub after_end: u64,
    /// Packets before the stream header (a stray packet, the tail of another stream).
    pub before_header: u64,
    /// Version 2: no end packet, or totals that disagree with what arrived.
    pub truncated: bool,
    /// The end packet's totals (`None`: no end packet arrived).
    pub end_totals: Option<TotalsReport>,
    /// The first [`MAX_GAP_ENTRIES`] gap records, in arrival order.
    pub gaps: Vec<GapEntry>,
    /// Gap records accepted (all of them, also those not listed in `gaps`).
    pub gap_records: u64,
    /// Board rows in the accepted gap records.
    pub gap_rows: u64,
    /// Board rows between the first and the last row or gap that no packet covers.
    pub rows_missing: u64,
    /// Frame trigger records accepted (the stream's trigger log, one per frame the frame
    /// grabber took; 0 in streams made before trigger records).
    pub triggers: u64,
}

/// The end packet's totals.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct TotalsReport {
    /// Packets of the stream, the stream header and the end packet included.
    pub packets: u64,
    /// Row packets.
    pub rows: u64,
    /// Board rows inside gap records.
    pub gap_rows: u64,
    /// First board row covered by a row or gap (0 when none).
    pub first_row: i64,
    /// Last board row covered by a row or gap (-1 when none).
    pub last_row: i64,
}

impl From<Totals> for TotalsReport {
    fn from(t: Totals) -> Self {
        TotalsReport {
            packets: t.packets,
            rows: t.rows,
            gap_rows: t.gap_rows,
            first_row: t.first_row,
            last_row: t.last_row,
        }
    }
}

/// Counts of a decoded stream.
#[derive(Clone, Debug, Default, Serialize)]
pub struct DecodeReport {
    /// Packets whose framing and CRC checked out and that were used.
    pub ok: usize,
    /// Damage reports: bytes that are not a packet, packets that do not unpack, packets of
    /// another width (each counted; the first [`MAX_DAMAGE_ENTRIES`] listed in `damage`).
    pub corrupt: usize,
    /// Times the decoder had to search for the next sync word.
    pub resynced: usize,
    /// The first [`MAX_DAMAGE_ENTRIES`] damage reports, sorted by offset.
    pub damage: Vec<Damage>,
    /// Bytes read.
    pub bytes: u64,
    /// What the stream said about itself.
    pub stream: StreamReport,
}

/// How `dpsa decode` ends (its exit status).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DecodeOutcome {
    /// Everything decoded; a version 2 stream ended with matching totals.
    Clean = 0,
    /// Rows decoded, but damage, missing / duplicated / reordered packets or a truncated stream.
    Damaged = 2,
    /// No decodable row.
    Nothing = 3,
}

impl DecodeReport {
    /// The exit status class of a decode that gave `map`.
    pub fn verdict(&self, map: &HeightMap) -> DecodeOutcome {
        self.verdict_rows(map.rows.len() as u64)
    }

    /// The exit status class of a decode that gave `rows` decoded rows.
    pub fn verdict_rows(&self, rows: u64) -> DecodeOutcome {
        let s = &self.stream;
        if rows == 0 && s.gap_records == 0 {
            DecodeOutcome::Nothing
        } else if self.corrupt > 0
            || s.missing > 0
            || s.duplicated > 0
            || s.reordered > 0
            || s.row_order > 0
            || s.wrong_width > 0
            || s.other_camera > 0
            || s.after_end > 0
            || s.before_header > 0
            || s.truncated
            || s.rows_missing > 0
        {
            DecodeOutcome::Damaged
        } else {
            DecodeOutcome::Clean
        }
    }

    fn damage(&mut self, offset: u64, e: impl ToString) {
        self.corrupt += 1;
        if self.damage.len() < MAX_DAMAGE_ENTRIES {
            self.damage.push(Damage {
                offset: offset as usize,
                error: e.to_string(),
            });
        }
    }
}

/// Decodes a whole packet stream held in memory (see [`decode_reader`]).
pub fn decode_stream(bytes: &[u8], lsb_um: f64) -> (HeightMap, DecodeReport) {
    decode_reader(bytes, lsb_um).expect("reading a slice cannot fail")
}

/// What [`decode_reader_with`] keeps of the decoded rows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Keep {
    /// Keep the rows' heights (for a height map); otherwise only their counts.
    pub rows: bool,
    /// Largest number of pixels kept as heights; past it the decode gives no map
    /// ([`Decoded::map`] is `None`, [`Decoded::over_limit`] true) and goes on counting.
    pub max_pixels: u64,
}

/// Pixels of a height map `dpsa decode --png` and `dpsa codec-bench` keep at most (2^26 =
/// 67 Mpx, ~200 MB of heights and validity): a stream of a larger map still decodes and is
/// counted, but gives no map.
pub const MAX_MAP_PIXELS: u64 = 1 << 26;

/// Frame triggers a decode keeps at most (2^24; 24 bytes each while decoding, 16 after): more
/// than a stream of a map of [`MAX_MAP_PIXELS`] holds at one frame per board row of a camera
/// 4 px wide.
pub const MAX_TRIGGERS: usize = 1 << 24;

/// Rows decoded from a stream, each board row counted once.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct RowCounts {
    /// Rows decoded at the stream's width.
    pub decoded: u64,
    /// Of them, rows without an invalidating flag.
    pub valid: u64,
    /// Valid pixels (valid bit set in a valid row).
    pub valid_pixels: u64,
    /// `decoded x width`.
    pub total_pixels: u64,
}

/// The result of [`decode_reader_with`].
#[derive(Clone, Debug)]
pub struct Decoded {
    /// The height map, when rows were kept and stayed within the limit.
    pub map: Option<HeightMap>,
    /// The rows' counts (always complete).
    pub rows: RowCounts,
    /// The map would have exceeded [`Keep::max_pixels`].
    pub over_limit: bool,
    /// The stream's trigger log in packet order (kept with the rows, [`Keep::rows`]; at most
    /// [`MAX_TRIGGERS`], past it [`Decoded::triggers_over_limit`]): every frame's counter and
    /// latch.
    pub triggers: Vec<Trigger>,
    /// The stream held more than [`MAX_TRIGGERS`] trigger records: `triggers` is incomplete.
    pub triggers_over_limit: bool,
    /// The damage and stream report.
    pub report: DecodeReport,
}

/// A decoded row: whole, or (when rows are not kept) what the counts need.
#[derive(Clone, Debug)]
enum Kept {
    Row(Box<HeightRow>),
    Counts {
        row: i64,
        width: usize,
        valid_row: bool,
        valid_pixels: u32,
    },
}

impl Kept {
    fn row(&self) -> i64 {
        match self {
            Kept::Row(r) => r.row,
            Kept::Counts { row, .. } => *row,
        }
    }
    fn width(&self) -> usize {
        match self {
            Kept::Row(r) => r.heights.len(),
            Kept::Counts { width, .. } => *width,
        }
    }
}

/// The decoder's state between chunks.
struct Decoder {
    map: HeightMap,
    rep: DecodeReport,
    tracker: Tracker,
    /// Codec reference state per width (at most 4 widths; one serves a whole stream so that
    /// predicted rows find their reference).
    refs: Vec<(usize, codec::ReferenceRow)>,
    /// Sequence number of the last version 2 packet followed: a packet that does not come
    /// next drops the references, so that a predicted row is never decoded against a row from
    /// before a loss (the codec's 8-bit row sequence misses a loss of 256 rows).
    last_seq: Option<u32>,
    /// Decoded rows with their offsets (width chosen at the end). Without kept heights an
    /// entry is 32 bytes, less than the smallest packet (44 bytes, 36 for version 1): memory
    /// stays below the input's size.
    rows: Vec<(u64, Kept)>,
    keep: Keep,
    kept_pixels: u64,
    over_limit: bool,
    /// Trigger records kept, with their packets' sequence numbers (24 bytes each, less than
    /// the 44-byte record they came from).
    triggers: Vec<(u32, Trigger)>,
    triggers_over_limit: bool,
    /// Rows handed on already ([`Live::take_rows`]): counted in the report, no longer kept.
    taken: u64,
}

impl Decoder {
    fn new(lsb_um: f64, keep: Keep) -> Decoder {
        Decoder {
            map: HeightMap::new(0, lsb_um),
            rep: DecodeReport::default(),
            tracker: Tracker::new(),
            refs: Vec::new(),
            last_seq: None,
            rows: Vec::new(),
            keep,
            kept_pixels: 0,
            over_limit: false,
            triggers: Vec::new(),
            triggers_over_limit: false,
            taken: 0,
        }
    }

    fn packet(&mut self, offset: u64, p: &Packet<'_>) {
        // A stream carries one camera: a packet of another (spliced in from another camera's
        // stream) is not followed at all, as if it were garbage.
        if let Some(info) = self.tracker.summary().info {
            if p.header.camera != info.camera {
                self.rep.stream.other_camera += 1;
                self.rep.damage(
                    offset,
                    format!(
                        "camera {} differs from the stream's camera {}",
                        p.header.camera, info.camera
                    ),
                );
                return;
            }
        }
        match self.tracker.packet(p) {
            Verdict::Accept => {
                if p.version == packets::VERSION {
                    if self.last_seq.is_some_and(|s| p.seq != s.wrapping_add(1)) {
                        self.refs.clear();
                    }
                    self.last_seq = Some(p.seq);
                }
            }
            Verdict::Duplicate => return,
            Verdict::WrongWidth => {
                let w = self.tracker.summary().info.map_or(0, |i| i.width);
                self.rep.damage(
                    offset,
                    format!(
                        "width {} differs from the stream's width {w}",
                        p.header.width
                    ),
                );
                return;
            }
        }
        match p.kind {
            Kind::Row => self.row(offset, p),
            Kind::Gap => {
                self.rep.ok += 1;
                if let Some(g) = p.gap() {
                    if self.rep.stream.gaps.len() < MAX_GAP_ENTRIES {
                        self.rep.stream.gaps.push(GapEntry {
                            first: g.first,
                            count: g.count,
                            flags: g.flags,
                        });
                    }
                }
            }
            Kind::Trigger => {
                self.rep.ok += 1;
                if let Some(t) = p.trigger() {
                    if self.keep.rows {
                        if self.triggers.len() < MAX_TRIGGERS {
                            self.triggers.push((p.seq, t));
                        } else {
                            self.triggers_over_limit = true;
                        }
                    }
                }
            }
            Kind::StreamHeader | Kind::End => self.rep.ok += 1,
        }
    }

    fn row(&mut self, offset: u64, p: &Packet<'_>) {
        let w = p.header.width as usize;
        let mut heights = vec![0i16; w];
        let mut bits = vec![0u8; w.div_ceil(8)];
        if !self.refs.iter().any(|(rw, _)| *rw == w) {
            if self.refs.len() >= 4 {
                self.refs.remove(0);
            }
            self.refs.push((w, codec::ReferenceRow::new(w)));
        }
        let res = match self.refs.iter_mut().find(|(rw, _)| *rw == w) {
            Some((_, r)) => match r.decoder() {
                Some(mut d) => p.unpack(&mut d, &mut heights, &mut bits),
                None => Err(PacketError::BadLength),
            },
            None => Err(PacketError::BadLength),
        };
        match res {
            Ok(()) => {
                let valid: Vec<bool> = (0..w).map(|c| bits[c / 8] & (1 << (c % 8)) != 0).collect();
                let row = HeightRow {
                    row: p.header.row,
                    latch: p.header.latch,
                    flags: p.header.flags,
                    heights,
                    valid,
                };
                let fits = self.kept_pixels.saturating_add(w as u64) <= self.keep.max_pixels;
                if self.keep.rows && !fits {
                    self.over_limit = true;
                }
                let kept = if self.keep.rows && fits {
                    self.kept_pixels += w as u64;
                    Kept::Row(Box::new(row))
                } else {
                    Kept::Counts {
                        row: row.row,
                        width: w,
                        valid_row: row.is_valid(),
                        valid_pixels: row.valid_count() as u32,
                    }
                };
                self.rows.push((offset, kept));
                self.rep.ok += 1;
            }
            Err(e) => self.rep.damage(offset, e),
        }
    }

    fn finish(mut self) -> Decoded {
        let s: Summary = self.tracker.summary();
        // The map's width: the stream header's, else the most common among decoded rows.
        let width = match s.info {
            Some(i) => i.width as usize,
            None => {
                let mut counts: Vec<(usize, usize)> = Vec::new();
                for (_, r) in &self.rows {
                    match counts.iter_mut().find(|(w, _)| *w == r.width()) {
                        Some(c) => c.1 += 1,
                        None => counts.push((r.width(), 1)),
                    }
                }
                // Most rows; on a tie the width that came first.
                counts
                    .iter()
                    .fold(None::<(usize, usize)>, |best, &c| match best {
                        Some(b) if b.1 >= c.1 => Some(b),
                        _ => Some(c),
                    })
                    .map_or(0, |c| c.0)
            }
        };
        let mut other = Vec::new();
        let mut rows = Vec::with_capacity(self.rows.len());
        for (off, r) in self.rows.drain(..) {
            if r.width() == width {
                rows.push(r);
            } else {
                other.push((off, r.width()));
            }
        }
        for (off, w) in other {
            self.rep.ok -= 1;
            self.rep.damage(
                off,
                format!("width {w} differs from the stream's width {width}"),
            );
        }
        self.rep.damage.sort_by_key(|d| d.offset);
        // Rows by board row; a board row that arrived twice counts once (the first copy).
        rows.sort_by_key(Kept::row);
        let before = rows.len();
        rows.dedup_by_key(|r| r.row());
        let dup_rows = (before - rows.len()) as u64;
        let mut counts = RowCounts::default();
        for r in &rows {
            let (valid_row, valid_pixels) = match r {
                Kept::Row(r) => (r.is_valid(), r.valid_count() as u64),
                Kept::Counts {
                    valid_row,
                    valid_pixels,
                    ..
                } => (*valid_row, u64::from(*valid_pixels)),
            };
            counts.decoded += 1;
            counts.valid += u64::from(valid_row);
            counts.valid_pixels += valid_pixels;
            counts.total_pixels += width as u64;
        }
        let n_rows = rows.len() as u128 + u128::from(self.taken);
        let map = if self.keep.rows && !self.over_limit {
            self.map.width = if rows.is_empty() { 0 } else { width };
            self.map.rows = rows
                .into_iter()
                .filter_map(|r| match r {
                    Kept::Row(r) => Some(*r),
                    Kept::Counts { .. } => None,
                })
                .collect();
            Some(self.map)
        } else {
            None
        };
        let st = &mut self.rep.stream;
        st.version = s.version;
        if let Some(i) = s.info {
            st.camera = Some(i.camera);
            st.width = Some(i.width);
            st.run_id = Some(i.run_id);
            st.config_hash = Some(format!("{:016x}", i.config_hash));
            st.intra_period = Some(i.intra_period);
            st.n = Some(i.n);
            st.frame_rows = Some(i.rows);
            st.max_step_rows = Some(i.max_step_rows);
        }
        st.missing = s.missing;
        st.duplicated = s.duplicated + if s.version == 1 { dup_rows } else { 0 };
        st.reordered = s.reordered;
        st.row_order = s.row_order;
        st.wrong_width = s.wrong_width;
        st.after_end = s.after_end;
        st.before_header = s.before_header;
        st.truncated = s.truncated;
        st.end_totals = s.totals.map(Into::into);
        st.gap_records = s.gaps;
        st.gap_rows = s.gap_rows;
        st.triggers = s.triggers;
        // Frame order is packet order (a late packet goes back to its place).
        self.triggers.sort_by_key(|t| t.0);
        let triggers = self.triggers.into_iter().map(|t| t.1).collect();
        if s.first_row <= s.last_row {
            let span = (s.last_row as i128 - s.first_row as i128 + 1) as u128;
            let covered = n_rows + s.gap_rows as u128;
            st.rows_missing = span.saturating_sub(covered).min(u64::MAX as u128) as u64;
        }
        Decoded {
            map,
            rows: counts,
            over_limit: self.over_limit,
            triggers,
            triggers_over_limit: self.triggers_over_limit,
            report: self.rep,
        }
    }
}

/// Decodes a packet stream read from `input` in chunks of 64 KiB, in memory bounded by the
/// chunk, the decoded rows and the capped report lists, and time linear in the input. Damage
/// never stops the decoder: it reports the packet and resynchronises on the next sync word.
/// Rows are placed by their board row (`map.rows` sorted, one per board row); `lsb_um` labels
/// the heights (the stream carries LSBs).
pub fn decode_reader<R: Read>(input: R, lsb_um: f64) -> std::io::Result<(HeightMap, DecodeReport)> {
    let keep = Keep {
        rows: true,
        max_pixels: u64::MAX,
    };
    let d = decode_reader_with(input, lsb_um, keep)?;
    let map = d.map.unwrap_or_else(|| HeightMap::new(0, lsb_um));
    Ok((map, d.report))
}

/// [`decode_reader`] keeping the rows' heights only as `keep` says: without heights the memory
/// is the chunk, a 32-byte entry per decoded row (less than the row's packet took in the
/// input) and the capped report lists.
pub fn decode_reader_with<R: Read>(
    mut input: R,
    lsb_um: f64,
    keep: Keep,
) -> std::io::Result<Decoded> {
    let mut d = Decoder::new(lsb_um, keep);
    let mut walk = Walk::new();
    let mut buf: Vec<u8> = Vec::with_capacity(CHUNK + MAX_PACKET_LEN);
    let mut base = 0u64;
    let mut eof = false;
    loop {
        while let Some(item) = walk.next(&buf, eof) {
            match item {
                Item::Packet { offset, packet } => d.packet(base + offset as u64, &packet),
                Item::Damage { offset, error } => {
                    // Version 1 packets carry no sequence number: bytes that are not a packet
                    // may have held rows, so the references go.
                    if d.tracker.summary().version != packets::VERSION {
                        d.refs.clear();
                    }
                    d.tracker.damage();
                    d.rep.damage(base + offset as u64, error);
                    d.rep.resynced += 1;
                }
            }
        }
        if eof {
            break;
        }
        // Drop what the walk is done with, then top the buffer up (a packet is at most
        // MAX_PACKET_LEN bytes, so the walk can always decide its next item).
        let done = walk.position().min(buf.len());
        buf.drain(..done);
        walk.shift(done);
        base += done as u64;
        let have = buf.len();
        buf.resize(have + CHUNK, 0);
        let mut got = 0;
        while got < CHUNK {
            match input.read(&mut buf[have + got..]) {
                Ok(0) => {
                    eof = true;
                    break;
                }
                Ok(n) => got += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        buf.truncate(have + got);
        d.rep.bytes += got as u64;
    }
    Ok(d.finish())
}

/// A stream decoded as its bytes arrive (a frame grabber's link): the same decoder as
/// [`decode_reader_with`], fed piece by piece, its rows and trigger records handed on as they
/// come ([`Live::take_rows`], [`Live::take_triggers`]). It stops right after the end packet:
/// bytes after it are the next stream's ([`Live::finish`] gives them back). Memory: the bytes
/// of at most one unfinished packet plus what was pushed since the last take.
pub struct Live {
    d: Decoder,
    walk: Walk,
    buf: Vec<u8>,
    /// Whether the end packet was decoded (nothing after it is looked at).
    ended: bool,
}

impl Live {
    /// A decoder at the start of a stream whose heights are in LSB of `lsb_um`.
    pub fn new(lsb_um: f64) -> Live {
        let keep = Keep {
            rows: true,
            max_pixels: u64::MAX,
        };
        Live {
            d: Decoder::new(lsb_um, keep),
            walk: Walk::new(),
            buf: Vec::new(),
            ended: false,
        }
    }

    /// Decodes what `bytes` completes (damage reported and skipped as in a file); after the
    /// end packet the bytes are only kept.
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
        self.walk_on(false);
    }

    fn walk_on(&mut self, eof: bool) {
        while !self.ended {
            let Some(item) = self.walk.next(&self.buf, eof) else {
                break;
            };
            let base = self.d.rep.bytes;
            match item {
                Item::Packet { offset, packet } => {
                    self.d.packet(base + offset as u64, &packet);
                    // The end packet closes the stream once the tracker took it.
                    self.ended =
                        packet.kind == Kind::End && self.d.tracker.summary().totals.is_some();
                }
                Item::Damage { offset, error } => {
                    // As in a file: version 1 damage may have held rows, so the references go.
                    if self.d.tracker.summary().version != packets::VERSION {
                        self.d.refs.clear();
                    }
                    self.d.tracker.damage();
                    self.d.rep.damage(base + offset as u64, error);
                    self.d.rep.resynced += 1;
                }
            }
        }
        let done = self.walk.position().min(self.buf.len());
        self.buf.drain(..done);
        self.walk.shift(done);
        self.d.rep.bytes += done as u64;
    }

    /// The stream header's contents, once it arrived.
    pub fn info(&self) -> Option<dpsa_core::row::StreamInfo> {
        self.d.tracker.summary().info
    }

    /// The end packet arrived: the stream is complete (its report in [`Live::finish`]).
    pub fn ended(&self) -> bool {
        self.ended
    }

    /// Bytes received and not yet decoded (at most an unfinished packet, or after the end
    /// packet the next stream's bytes).
    pub fn pending(&self) -> usize {
        self.buf.len()
    }

    /// The rows decoded since the last call, in arrival order.
    pub fn take_rows(&mut self) -> Vec<HeightRow> {
        self.d.taken += self.d.rows.len() as u64;
        self.d.kept_pixels = 0;
        self.d
            .rows
            .drain(..)
            .filter_map(|(_, r)| match r {
                Kept::Row(r) => Some(*r),
                Kept::Counts { .. } => None,
            })
            .collect()
    }

    /// The frame trigger records decoded since the last call, in packet order.
    pub fn take_triggers(&mut self) -> Vec<Trigger> {
        self.d.triggers.sort_by_key(|t| t.0);
        self.d.triggers.drain(..).map(|t| t.1).collect()
    }

    /// The stream's report (what [`decode_reader_with`] reports, rows taken or not), and the
    /// bytes that came after its end packet (the next stream's start). Without the end packet
    /// (a link cut) the rest of the bytes are walked to their end first.
    pub fn finish(mut self) -> (DecodeReport, Vec<u8>) {
        if !self.ended {
            self.walk_on(true);
        }
        let rest = std::mem::take(&mut self.buf);
        self.d.rows.clear();
        (self.d.finish().report, rest)
    }
}

#[cfg(test)]
mod size_tests {
    /// The per-row entry kept without heights stays at 32 bytes (below any packet's size).
    #[test]
    fn counted_rows_take_32_bytes() {
        assert_eq!(size_of::<(u64, super::Kept)>(), 32);
    }
}

#[cfg(test)]
mod live_tests {
    use super::*;
    use dpsa_core::packets::{encode_end, encode_raw, encode_stream_header, encode_trigger};
    use dpsa_core::row::StreamInfo;
    use dpsa_core::{Row, RowHeader};

    const W: u16 = 20;

    /// A version 2 stream of `rows` rows of camera 1 with a trigger record before each row.
    fn stream(rows: i64, run_id: u64) -> Vec<u8> {
        let mut out = Vec::new();
        let mut buf = vec![0u8; packets::max_packet_len(W as usize)];
        let info = StreamInfo {
            camera: 1,
            n: 4,
            width: W,
            rows: 16,
            max_step_rows: 5,
            config_hash: 0xabcd,
            run_id,
            intra_period: 1,
        };
        let n = encode_stream_header(&info, &mut buf).unwrap();
        out.extend_from_slice(&buf[..n]);
        let mut seq = 1;
        for r in 0..rows {
            let t = Trigger {
                seq: r as u32,
                latch: 100 * r,
            };
            let n = encode_trigger(&t, 1, 4, W, seq, &mut buf).unwrap();
            out.extend_from_slice(&buf[..n]);
            seq += 1;
            let heights: Vec<i16> = (0..W as i16).map(|c| c * 7 - r as i16).collect();
            let valid = vec![0xffu8, 0x0f, 0x05];
            let row = Row {
                header: RowHeader {
                    camera: 1,
                    n: 4,
                    row: 10 + r,
                    latch: 100 * r,
                    flags: 0,
                    width: W,
                },
                heights: &heights,
                valid: &valid,
            };
            let n = encode_raw(&row, seq, &mut buf).unwrap();
            out.extend_from_slice(&buf[..n]);
            seq += 1;
        }
        let totals = Totals {
            packets: u64::from(seq) + 1,
            rows: rows as u64,
            gap_rows: 0,
            first_row: 10,
            last_row: 10 + rows - 1,
        };
        let n = encode_end(&totals, 1, 4, W, seq, &mut buf).unwrap();
        out.extend_from_slice(&buf[..n]);
        out
    }

    /// Fed in pieces of any size, the live decoder gives the rows, triggers and report of
    /// the whole-stream decoder, stops at the end packet and hands back the next stream's
    /// bytes untouched.
    #[test]
    fn live_pieces_give_the_whole_decode_and_the_next_stream() {
        let first = stream(30, 7);
        let second = stream(5, 8);
        let (map, whole) = decode_stream(&first, 0.25);
        let both: Vec<u8> = first.iter().chain(&second).copied().collect();
        for piece in [1usize, 3, 44, 500, 100_000] {
            let mut live = Live::new(0.25);
            let (mut rows, mut triggers) = (Vec::new(), Vec::new());
            let mut fed = 0;
            while fed < both.len() && !live.ended() {
                let end = (fed + piece).min(both.len());
                live.push(&both[fed..end]);
                fed = end;
                rows.extend(live.take_rows());
                triggers.extend(live.take_triggers());
            }
            assert!(live.ended(), "piece {piece}");
            assert_eq!(live.info().map(|i| i.run_id), Some(7));
            let (rep, mut rest) = live.finish();
            rest.extend_from_slice(&both[fed..]);
            assert_eq!(rest, second, "piece {piece}: the next stream's bytes");
            assert_eq!(rows.len(), map.rows.len());
            for (a, b) in rows.iter().zip(&map.rows) {
                assert_eq!(
                    (a.row, a.latch, &a.heights, &a.valid),
                    (b.row, b.latch, &b.heights, &b.valid)
                );
            }
            assert_eq!(triggers.len(), 30);
            assert_eq!(triggers[29].latch, 2900);
            assert_eq!(rep.ok, whole.ok);
            assert_eq!(rep.bytes, first.len() as u64);
            assert!(!rep.stream.truncated && rep.stream.rows_missing == 0 && rep.corrupt == 0);
            assert_eq!(rep.verdict_rows(rows.len() as u64), DecodeOutcome::Clean);
        }
    }

    /// A link cut mid-stream: the report says truncated, and damage inside is counted.
    #[test]
    fn a_cut_stream_is_truncated_and_damage_is_counted() {
        let mut s = stream(30, 7);
        s.truncate(s.len() / 2);
        s[300] ^= 0x40;
        let mut live = Live::new(0.25);
        live.push(&s);
        let rows = live.take_rows();
        assert!(!live.ended());
        let (rep, rest) = live.finish();
        assert!(rest.is_empty());
        assert!(rep.stream.truncated);
        assert!(rep.corrupt >= 1);
        assert!(!rows.is_empty());
        assert_eq!(rep.verdict_rows(rows.len() as u64), DecodeOutcome::Damaged);
    }
}
