//! Following a stream: sequence numbers, board rows, the stream header's width and the end
//! packet's totals, in O(1) memory (a 1024-packet window of seen sequence numbers).
//!
//! Feed every [`Item`](super::Item) of a walk to [`Tracker::packet`] / [`Tracker::damage`], then
//! read [`Tracker::summary`]. Version 1 packets carry no sequence numbers: for them only the
//! board-row order and the widths are followed.

use super::{Kind, Packet, Totals, VERSION};
use crate::row::StreamInfo;

/// Sequence numbers remembered behind the newest one, to tell a duplicate from a late packet.
pub const SEQ_WINDOW: u32 = 1024;

/// What to do with a packet.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Use it (it may be late: rows are placed by their board row).
    Accept,
    /// Its sequence number was seen already (or is older than `SEQ_WINDOW`): drop it.
    Duplicate,
    /// A row or gap of another width than the stream header's: drop it.
    WrongWidth,
}

/// Counts and findings of a stream so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Summary {
    /// Version of the first packet (0 if none).
    pub version: u8,
    /// The stream header, if one arrived.
    pub info: Option<StreamInfo>,
    /// The end packet's totals, if one arrived.
    pub totals: Option<Totals>,
    /// Packets accepted (duplicates and wrong widths excluded), any kind.
    pub packets: u64,
    /// Row packets accepted.
    pub rows: u64,
    /// Gap records accepted.
    pub gaps: u64,
    /// Board rows in the accepted gap records.
    pub gap_rows: u64,
    /// Frame trigger records accepted.
    pub triggers: u64,
    /// Lowest board row covered by accepted rows and gaps (`first_row > last_row`: none).
    pub first_row: i64,
    /// Highest board row covered by accepted rows and gaps.
    pub last_row: i64,
    /// Sequence numbers never seen below the highest one seen (version 2), plus the packets
    /// after it that the end packet's total says exist.
    pub missing: u64,
    /// Packets whose sequence number was seen already.
    pub duplicated: u64,
    /// Packets that arrived after a packet with a higher sequence number.
    pub reordered: u64,
    /// Accepted rows or gaps whose board row is not above every row before them in arrival
    /// order (a reordered or damaged stream).
    pub row_order: u64,
    /// Packets of another width than the stream header's.
    pub wrong_width: u64,
    /// Packets after the end packet (by arrival).
    pub after_end: u64,
    /// Version 2 packets that arrived before the stream header (a stray packet or the tail of
    /// another stream; the header restarts the sequence bookkeeping).
    pub before_header: u64,
    /// Damage items (bytes that were not a packet).
    pub damage: u64,
    /// Version 2: no end packet, or its totals disagree with what arrived.
    pub truncated: bool,
    /// Version 2 with an end packet: its totals match what arrived.
    pub totals_agree: bool,
}

impl Summary {
    /// True when nothing was lost, repeated, reordered or damaged and a version 2 stream ended
    /// with matching totals.
    pub fn clean(&self) -> bool {
        self.missing == 0
            && self.duplicated == 0
            && self.reordered == 0
            && self.row_order == 0
            && self.wrong_width == 0
            && self.after_end == 0
            && self.damage == 0
            && !self.truncated
    }
}

fn bit(seq: u32) -> (usize, u64) {
    let i = (seq % SEQ_WINDOW) as usize;
    (i / 64, 1u64 << (i % 64))
}

/// The stream follower.
#[derive(Clone, Debug)]
pub struct Tracker {
    s: Summary,
    /// Sequence numbers seen, bit `seq % SEQ_WINDOW`, valid for `[next - SEQ_WINDOW, next)`.
    seen: [u64; (SEQ_WINDOW / 64) as usize],
    /// One past the highest sequence number seen (`None`: none yet).
    next: Option<u32>,
    /// Highest board row covered so far, in arrival order.
    high: Option<i64>,
    ended: bool,
}

impl Default for Tracker {
    fn default() -> Self {
        Self::new()
    }
}

impl Tracker {
    /// A tracker that has seen nothing yet.
    pub fn new() -> Self {
        Tracker {
            s: Summary {
                first_row: 0,
                last_row: -1,
                ..Summary::default()
            },
            seen: [0; (SEQ_WINDOW / 64) as usize],
            next: None,
            high: None,
            ended: false,
        }
    }

    /// Bytes that were not a packet.
    pub fn damage(&mut self) {
        self.s.damage += 1;
    }

    /// Sequence bookkeeping: `false` for a duplicate.
    fn sequence(&mut self, seq: u32) -> bool {
        let Some(next) = self.next else {
            self.s.missing += seq as u64;
            self.next = Some(seq.wrapping_add(1));
            let (w, b) = bit(seq);
            self.seen[w] |= b;
            return true;
        };
        let ahead = seq.wrapping_sub(next) as i32;
        if ahead >= 0 {
            self.s.missing += ahead as u64;
            if ahead as u32 >= SEQ_WINDOW {
                self.seen = [0; (SEQ_WINDOW / 64) as usize];
            } else {
                for k in 0..ahead as u32 {
                    let (w, b) = bit(next.wrapping_add(k));
                    self.seen[w] &= !b;
                }
            }
            let (w, b) = bit(seq);
            self.seen[w] |= b;
            self.next = Some(seq.wrapping_add(1));
            return true;
        }
        let age = next.wrapping_sub(seq);
        let (w, b) = bit(seq);
        if age > SEQ_WINDOW || self.seen[w] & b != 0 {
            self.s.duplicated += 1;
            return false;
        }
        self.seen[w] |= b;
        self.s.missing = self.s.missing.saturating_sub(1);
        self.s.reordered += 1;
        true
    }

    /// Board rows `[first, first + count)` covered by an accepted row or gap.
    fn cover(&mut self, first: i64, count: u64) {
        let last = first.saturating_add(count.saturating_sub(1).min(i64::MAX as u64) as i64);
        if self.high.is_some_and(|h| first <= h) {
            self.s.row_order += 1;
        }
        self.high = Some(self.high.map_or(last, |h| h.max(last)));
        if self.s.first_row > self.s.last_row {
            self.s.first_row = first;
            self.s.last_row = last;
        } else {
            self.s.first_row = self.s.first_row.min(first);
            self.s.last_row = self.s.last_row.max(last);
        }
    }

    /// A well-framed packet.
    pub fn packet(&mut self, p: &Packet<'_>) -> Verdict {
        if self.s.version == 0 {
            self.s.version = p.version;
        }
        if p.version == VERSION && p.kind == Kind::StreamHeader && self.s.info.is_none() {
            // The stream starts here: what came before belongs to no stream of this header.
            self.s.before_header = self.s.packets;
            self.s.missing = 0;
            self.s.duplicated = 0;
            self.s.reordered = 0;
            self.next = None;
            self.seen = [0; (SEQ_WINDOW / 64) as usize];
        }
        if p.version == VERSION && !self.sequence(p.seq) {
            return Verdict::Duplicate;
        }
        if let Some(info) = self.s.info {
            if p.header.width != info.width {
                self.s.wrong_width += 1;
                return Verdict::WrongWidth;
            }
        }
        if self.ended {
            self.s.after_end += 1;
        }
        self.s.packets += 1;
        match p.kind {
            Kind::Row => {
                self.s.rows += 1;
                self.cover(p.header.row, 1);
            }
            Kind::Gap => {
                let g = p.gap().unwrap_or_default();
                self.s.gaps += 1;
                self.s.gap_rows = self.s.gap_rows.saturating_add(g.count);
                self.cover(g.first, g.count.max(1));
            }
            Kind::Trigger => self.s.triggers += 1,
            Kind::StreamHeader => {
                if self.s.info.is_none() {
                    self.s.info = p.stream_info();
                }
            }
            Kind::End => {
                if self.s.totals.is_none() {
                    self.s.totals = p.totals();
                }
                self.ended = true;
            }
        }
        Verdict::Accept
    }

    /// What the stream held, and whether it is complete (call at the end of the input).
    pub fn summary(&self) -> Summary {
        let mut s = self.s;
        if s.version == VERSION {
            match s.totals {
                None => s.truncated = true,
                Some(t) => {
                    let (first, last) = if s.first_row > s.last_row {
                        (0, -1)
                    } else {
                        (s.first_row, s.last_row)
                    };
                    s.missing += t.packets.saturating_sub(self.next.unwrap_or(0) as u64);
                    s.totals_agree = t.packets == s.packets
                        && t.rows == s.rows
                        && t.gap_rows == s.gap_rows
                        && t.first_row == first
                        && t.last_row == last;
                    s.truncated = !s.totals_agree;
                }
            }
        }
        s
    }
}
