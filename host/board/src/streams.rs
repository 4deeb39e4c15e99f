//! `dpsa board --streams`: the cameras' packet streams (what a line receives from its frame
//! grabbers) as the rows of the board map. They need the calibration file and the array's
//! `array.json` only: no camera recording, no frame.
//!
//! Each stream is read in chunks with the stream decoder (a regular file, at most
//! [`max_stream_bytes`] read, at most [`stream::MAX_MAP_PIXELS`] heights kept) and matched to its
//! camera by the camera id of its stream header, in any order. Refused, before any file is
//! written: a stream without a header, a camera missing, given twice or not in the
//! calibration, a width other than the calibration's, run ids that differ between the streams
//! ("streams from different boards") or from the board identity of `array.json`, a
//! configuration hash other than the calibration file's configuration of that camera gives
//! (another calibration, LSB or processing; `dpsa_stream::config::of_calibration`).
//!
//! Damage does not stop the map: the board rows a stream lacks (missing or damaged packets,
//! a truncated end) are *lost*. They are the rows between the stream's first and last row
//! (the end packet's totals, or, without an end packet, up to where the camera sees the
//! board) that no row packet and no gap record covers; the map keeps their board pixels
//! invalid (never interpolated across, see [`crate::resample`]) and the report lists them.

use crate::output::BoardError;
use crate::provenance::Registration;
use crate::resample::{BoardGrid, CameraPlacement};
use dpsa_core::Trigger;
use dpsa_formats::calibration::{round_counts_per_pixel, CalFile, CameraCal};
use dpsa_formats::heightmap::HeightMap;
use dpsa_formats::BoardId;
use dpsa_stream::{self as stream, Damage, DecodeOutcome, DecodeReport, Keep};
use serde::Serialize;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

type Result<T> = std::result::Result<T, BoardError>;

/// Refuses with a sentence.
macro_rules! bail {
    ($($arg:tt)*) => {
        return Err(BoardError::Refused(format!($($arg)*)))
    };
}

/// Lost row ranges listed per camera in the report (the counts are complete).
pub const MAX_LOST_RANGES: usize = 100;

/// `streams.*` of `dpsa board --json`.
#[derive(Clone, Debug, Serialize)]
pub struct StreamsReport {
    /// Some stream was damaged or incomplete: the map has invalid areas for it.
    pub damaged: bool,
    /// As `dpsa decode`: 0 every stream clean, 2 damage, missing / duplicated / reordered
    /// packets, lost rows or a truncated stream.
    pub status: i32,
    /// Board rows lost per camera (camera order).
    pub missing_rows: Vec<u64>,
    /// Board-map pixels left invalid because a camera lost the rows that would have covered
    /// them and no other camera covered them.
    pub gap_board_pixels: u64,
    /// The board identity every stream carried as its run id (16 hex digits).
    pub run_id: String,
    /// Per camera (camera order).
    pub cameras: Vec<CameraStream>,
}

/// One camera's stream in the report.
#[derive(Clone, Debug, Serialize)]
pub struct CameraStream {
    /// The camera (its place in the array).
    pub camera: u8,
    /// The stream's file.
    pub file: String,
    /// Its size.
    pub bytes: u64,
    /// The configuration hash its header carries (16 hex digits).
    pub config_hash: String,
    /// Row packets decoded (each board row once).
    pub rows: u64,
    /// Board rows lost (see the module docs).
    pub missing_rows: u64,
    /// The first [`MAX_LOST_RANGES`] lost ranges `[first, last]` (board rows, inclusive).
    pub lost_ranges: Vec<[i64; 2]>,
    /// Packets decoded intact.
    pub packets_ok: usize,
    /// Damage reports (bytes that were not a packet, packets that did not unpack).
    pub damaged_packets: usize,
    /// Packets the sequence numbers say are missing.
    pub missing_packets: u64,
    /// Packets that arrived twice.
    pub duplicated_packets: u64,
    /// Packets out of order.
    pub reordered_packets: u64,
    /// No end packet, or its totals disagree with what arrived.
    pub truncated: bool,
    /// The stream's end packet arrived (without it the stream was cut off).
    pub end_packet: bool,
    /// Board rows inside gap records (never imaged: the encoder jumped; not lost).
    pub gap_rows: u64,
    /// The first damage entries, as `dpsa decode` lists them.
    pub damage: Vec<Damage>,
    /// 0 clean, 2 damaged or incomplete.
    pub status: i32,
}

/// One camera's rows from its stream.
pub struct Arrived {
    /// The stream's file.
    pub path: PathBuf,
    /// The rows, by board row.
    pub map: HeightMap,
    /// Lost board rows, inclusive ranges, clipped to where the camera sees the board.
    pub lost: Vec<(i64, i64)>,
    /// The stream's trigger log (every frame's counter and latch, frame order).
    pub triggers: Vec<Trigger>,
    /// What replaying the registration on `triggers` needs: the stream header's `H`, `n`,
    /// `max_step_rows`, the calibration's counts per pixel.
    pub registration: Registration,
}

/// One decoded stream: its rows, its trigger log and its report.
struct Decoded {
    map: HeightMap,
    triggers: Vec<Trigger>,
    report: DecodeReport,
}

/// The most bytes read from one stream: enough for [`stream::MAX_MAP_PIXELS`] heights of the
/// narrowest calibrated camera in the largest packets of the widest, plus 1 MiB. A larger
/// file is refused (it cannot be one camera's stream of a map this tool holds).
pub fn max_stream_bytes(cal: &CalFile) -> u64 {
    let narrow = cal.camera.iter().map(|c| c.width).min().unwrap_or(1).max(1);
    let wide = cal.camera.iter().map(|c| c.width).max().unwrap_or(1).max(1);
    let rows = stream::MAX_MAP_PIXELS / u64::from(narrow) + 16;
    rows * dpsa_core::packets::max_packet_len(wide as usize) as u64 + (1 << 20)
}

/// The camera rows (inclusive) whose pixels can land on the board grid: the camera's columns
/// over the board's length, one row of margin.
pub fn board_extent(p: &CameraPlacement, grid: &BoardGrid, width: u32) -> (i64, i64) {
    let x_end = grid.x0_mm + grid.rows as f64 * grid.pitch_mm;
    let s = p.rotation_rad.sin();
    let mut lo = f64::INFINITY;
    let mut hi = f64::NEG_INFINITY;
    for x in [grid.x0_mm, x_end] {
        for c in [0.0, f64::from(width.saturating_sub(1))] {
            let b = (x - p.x0_mm - c * p.pitch_mm * s) / p.row_mm;
            lo = lo.min(b);
            hi = hi.max(b);
        }
    }
    let clamp = |v: f64| v.clamp(-1e15, 1e15) as i64;
    (clamp(lo.floor()) - 1, clamp(hi.ceil()) + 1)
}

/// Decodes one stream file in bounded memory.
fn read(path: &Path, lsb_um: f64, max_bytes: u64) -> Result<Decoded> {
    let file = dpsa_formats::files::open_regular(path, "packet stream")?;
    let keep = Keep {
        rows: true,
        max_pixels: stream::MAX_MAP_PIXELS,
    };
    let d = stream::decode_reader_with(BufReader::new(file.take(max_bytes + 1)), lsb_um, keep)
        .map_err(|e| BoardError::Refused(format!("cannot read {}: {e}", path.display())))?;
    if d.report.bytes > max_bytes {
        bail!(
            "packet stream {} is larger than {max_bytes} bytes, more than one camera's stream of \
             a board map can be",
            path.display()
        );
    }
    if d.over_limit {
        bail!(
            "packet stream {} holds more than {} Mpx of heights, more than one camera of a board \
             map can have",
            path.display(),
            stream::MAX_MAP_PIXELS >> 20
        );
    }
    if d.triggers_over_limit {
        bail!(
            "packet stream {} holds more than {} frame trigger records, more than one camera of \
             a board map can have",
            path.display(),
            stream::MAX_TRIGGERS
        );
    }
    let map = d.map.unwrap_or_else(|| HeightMap::new(0, lsb_um));
    Ok(Decoded {
        map,
        triggers: d.triggers,
        report: d.report,
    })
}

/// The configuration hash a stream of camera `i` carries when its frame grabber runs with the
/// calibration file `cal` (`dpsa_stream::config::of_calibration`).
pub fn expected_config_hash(cal: &CalFile, i: usize) -> Result<u64> {
    let core = dpsa_stream::config::of_calibration(cal, i)
        .map_err(|e| BoardError::Refused(format!("calibration camera {i}: {e}")))?;
    let (cfg, table) = (&core.cfg, &core.ref_phase);
    Ok(cfg.hash_with(
        &table[..usize::from(cfg.width).min(table.len())],
        core.columns().as_ref(),
    ))
}

/// Lost rows of a decoded stream (see the module docs): the ranges clipped to `extent`, the
/// count of all of them and the first [`MAX_LOST_RANGES`] unclipped.
fn lost_rows(
    map: &HeightMap,
    rep: &DecodeReport,
    extent: (i64, i64),
) -> (Vec<(i64, i64)>, u64, Vec<[i64; 2]>) {
    let s = &rep.stream;
    // What arrived: rows and gap records, as inclusive ranges.
    let mut covered: Vec<(i128, i128)> = map
        .rows
        .iter()
        .map(|r| (i128::from(r.row), i128::from(r.row)))
        .collect();
    covered.extend(s.gaps.iter().map(|g| {
        (
            i128::from(g.first),
            i128::from(g.first) + i128::from(g.count.max(1)) - 1,
        )
    }));
    covered.sort_unstable();
    let seen = covered
        .first()
        .map(|f| (f.0, covered.iter().map(|c| c.1).max().unwrap_or(f.1)));
    let (ext_lo, ext_hi) = (i128::from(extent.0), i128::from(extent.1));
    let (lo, hi) = match (s.end_totals, seen) {
        // The end packet says which rows the stream covers.
        (Some(t), seen) if t.first_row <= t.last_row => {
            let (a, b) = (i128::from(t.first_row), i128::from(t.last_row));
            seen.map_or((a, b), |(f, l)| (a.min(f), b.max(l)))
        }
        (Some(_), Some(seen)) => seen,
        (Some(_), None) => (1, 0),
        // No end packet: the stream may have gone on as far as the camera sees the board.
        (None, Some((f, l))) => (f.min(ext_lo), l.max(ext_hi)),
        (None, None) => (ext_lo, ext_hi),
    };
    let mut ranges = Vec::new();
    let mut count: u128 = 0;
    let mut listed = Vec::new();
    let mut lost = |a: i128, b: i128| {
        count += (b - a + 1) as u128;
        if listed.len() < MAX_LOST_RANGES {
            let n = |v: i128| v.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64;
            listed.push([n(a), n(b)]);
        }
        let (ca, cb) = (a.max(ext_lo), b.min(ext_hi));
        if ca <= cb {
            ranges.push((ca as i64, cb as i64));
        }
    };
    let mut cur = lo;
    for &(a, b) in &covered {
        if cur > hi {
            break;
        }
        if b < cur {
            continue;
        }
        if a > cur {
            lost(cur, (a - 1).min(hi));
        }
        cur = cur.max(b + 1);
    }
    if cur <= hi {
        lost(cur, hi);
    }
    (ranges, count.min(u128::from(u64::MAX)) as u64, listed)
}

/// Reads, checks and matches the streams at `paths` to the cameras of `cal` (board identity
/// `board` from `array_file`, board extents `extents`); returns each camera's rows in camera
/// order and the report (its `gap_board_pixels` filled in later).
pub fn read_streams(
    paths: &[PathBuf],
    cal: &CalFile,
    board: Option<BoardId>,
    array_file: &Path,
    extents: &[(i64, i64)],
) -> Result<(Vec<Arrived>, StreamsReport)> {
    let n = cal.camera.len();
    if paths.len() != n {
        bail!(
            "{} streams for {n} calibrated cameras: give one stream per camera",
            paths.len()
        );
    }
    let decoded = decode_all(paths, cal)?;
    let order = match_cameras(paths, &decoded, n)?;
    check_widths(paths, &decoded, &order, cal)?;
    let board = check_board(paths, &decoded, &order, board, array_file)?;
    check_configs(paths, &decoded, &order, cal)?;
    check_trigger_logs(paths, &decoded, &order)?;

    // Rows and what was lost, camera by camera.
    let mut slots: Vec<Option<Decoded>> = decoded.into_iter().map(Some).collect();
    let mut arrived = Vec::with_capacity(n);
    let mut cameras = Vec::with_capacity(n);
    for (i, &k) in order.iter().enumerate() {
        let Some(read) = slots[k].take() else {
            return Err(BoardError::Internal(format!("stream {k} matched twice")));
        };
        let (camera, rows) = camera_stream(i, &paths[k], read, &cal.camera[i], extents[i]);
        cameras.push(camera);
        arrived.push(rows);
    }
    let status = cameras.iter().map(|c| c.status).max().unwrap_or(0);
    Ok((
        arrived,
        StreamsReport {
            damaged: status != 0,
            status,
            missing_rows: cameras.iter().map(|c| c.missing_rows).collect(),
            gap_board_pixels: 0,
            run_id: board.to_string(),
            cameras,
        },
    ))
}

/// Decodes every stream (one thread each, at most [`max_stream_bytes`] of `cal` read).
fn decode_all(paths: &[PathBuf], cal: &CalFile) -> Result<Vec<Decoded>> {
    let max_bytes = max_stream_bytes(cal);
    std::thread::scope(|s| {
        let handles: Vec<_> = paths
            .iter()
            .map(|p| s.spawn(move || read(p, cal.height_lsb_um, max_bytes)))
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join().unwrap_or_else(|_| {
                    Err(BoardError::Internal("a decoder thread panicked".into()))
                })
            })
            .collect::<Result<Vec<_>>>()
    })
}

/// Matches the streams to the `n` cameras by the camera id of their stream headers: which
/// stream is camera `i`'s (one per camera, none twice, every id below `n`).
fn match_cameras(paths: &[PathBuf], decoded: &[Decoded], n: usize) -> Result<Vec<usize>> {
    let mut slot: Vec<Option<usize>> = vec![None; n];
    for (k, (path, Decoded { report: rep, .. })) in paths.iter().zip(decoded).enumerate() {
        let st = &rep.stream;
        let Some(camera) = st.camera else {
            bail!(
                "{}: no stream header (nothing decodable, a version 1 stream, or its header \
                 packet lost or damaged): it cannot be matched to a camera and a board",
                path.display()
            );
        };
        let i = usize::from(camera);
        if i >= n {
            bail!(
                "{} is camera {camera}'s stream; the calibration has cameras 0..={}",
                path.display(),
                n - 1
            );
        }
        if let Some(other) = slot[i] {
            bail!(
                "{} and {} are both camera {camera}'s stream: give one stream per camera",
                paths[other].display(),
                path.display()
            );
        }
        slot[i] = Some(k);
    }
    // One stream per camera: n streams, none twice, every id below n.
    Ok(slot.into_iter().map(|k| k.unwrap_or(0)).collect())
}

/// Each camera's stream is as wide as the calibration's camera.
fn check_widths(
    paths: &[PathBuf],
    decoded: &[Decoded],
    order: &[usize],
    cal: &CalFile,
) -> Result<()> {
    for (i, &k) in order.iter().enumerate() {
        let st = &decoded[k].report.stream;
        let w = st.width.map_or(0, u32::from);
        if w != cal.camera[i].width {
            bail!(
                "{} (camera {i}) is {w} px wide; the calibration's camera {i} is {} px wide",
                paths[k].display(),
                cal.camera[i].width
            );
        }
    }
    Ok(())
}

/// Every stream has the same run id, and it is the recording's board identity (returned).
fn check_board(
    paths: &[PathBuf],
    decoded: &[Decoded],
    order: &[usize],
    board: Option<BoardId>,
    array_file: &Path,
) -> Result<BoardId> {
    let run_of = |k: usize| decoded[k].report.stream.run_id.unwrap_or(0);
    let first = order[0];
    for &k in &order[1..] {
        if run_of(k) != run_of(first) {
            bail!(
                "streams from different boards: {} (camera {}) has run id {:016x}, {} (camera {}) \
                 {:016x}",
                paths[first].display(),
                decoded[first].report.stream.camera.unwrap_or(0),
                run_of(first),
                paths[k].display(),
                decoded[k].report.stream.camera.unwrap_or(0),
                run_of(k)
            );
        }
    }
    let Some(board) = board else {
        bail!(
            "{} has no board identity (it was recorded before board identities): its streams \
             cannot be told from another board's; record it again",
            array_file.display()
        );
    };
    if run_of(first) != board.0 {
        bail!(
            "the streams are of another board than {}: their run id is {:016x}, its board \
             identity is {board} (streams from different boards cannot make one map)",
            array_file.display(),
            run_of(first)
        );
    }
    Ok(board)
}

/// Each camera's stream was made with the configuration the calibration file gives that camera
/// (configuration hash).
fn check_configs(
    paths: &[PathBuf],
    decoded: &[Decoded],
    order: &[usize],
    cal: &CalFile,
) -> Result<()> {
    for (i, &k) in order.iter().enumerate() {
        let want = format!("{:016x}", expected_config_hash(cal, i)?);
        let have = decoded[k]
            .report
            .stream
            .config_hash
            .clone()
            .unwrap_or_default();
        if have != want {
            bail!(
                "{} (camera {i}) was made with another configuration than the calibration gives \
                 (configuration hash {have}, expected {want}: another calibration, height LSB or \
                 processing); make it with `--cal CAL --camera {i}`",
                paths[k].display()
            );
        }
    }
    Ok(())
}

/// Every stream carries its trigger log (streams made before trigger records have none, and a
/// stream that lost all of them cannot say where its rows came from).
fn check_trigger_logs(paths: &[PathBuf], decoded: &[Decoded], order: &[usize]) -> Result<()> {
    for (i, &k) in order.iter().enumerate() {
        let d = &decoded[k];
        if d.triggers.is_empty() && !d.map.rows.is_empty() {
            bail!(
                "{} (camera {i}) carries no frame trigger records (a stream made before they \
                 were part of the format, or every one was lost): which frames fed its rows, and \
                 so its dead-pixel masks and row places, cannot be known; make it again",
                paths[k].display()
            );
        }
    }
    Ok(())
}

/// Camera `i`'s report line and rows from its decoded stream at `path` (calibration `cal`,
/// board rows `extent`).
fn camera_stream(
    i: usize,
    path: &Path,
    read: Decoded,
    cal: &CameraCal,
    extent: (i64, i64),
) -> (CameraStream, Arrived) {
    let Decoded {
        map,
        triggers,
        report: rep,
    } = read;
    let (lost, missing, listed) = lost_rows(&map, &rep, extent);
    let verdict = rep.verdict(&map);
    let status = if verdict == DecodeOutcome::Clean && missing == 0 {
        0
    } else {
        DecodeOutcome::Damaged as i32
    };
    let st = &rep.stream;
    let camera = CameraStream {
        camera: i as u8,
        file: path.display().to_string(),
        bytes: rep.bytes,
        config_hash: st.config_hash.clone().unwrap_or_default(),
        rows: map.rows.len() as u64,
        missing_rows: missing,
        lost_ranges: listed,
        packets_ok: rep.ok,
        damaged_packets: rep.corrupt,
        missing_packets: st.missing,
        duplicated_packets: st.duplicated,
        reordered_packets: st.reordered,
        truncated: st.truncated,
        end_packet: st.end_totals.is_some(),
        gap_rows: st.gap_rows,
        damage: rep.damage.clone(),
        status,
    };
    let registration = Registration {
        rows: st.frame_rows.map_or(cal.rows, u32::from),
        n: st.n.unwrap_or(0),
        max_step_rows: st.max_step_rows.map_or(0, u32::from),
        counts_per_pixel: round_counts_per_pixel(cal.counts_per_pixel),
    };
    let arrived = Arrived {
        path: path.to_path_buf(),
        map,
        lost,
        triggers,
        registration,
    };
    (camera, arrived)
}

#[cfg(test)]
mod tests {
    use super::*;
    use dpsa_formats::heightmap::HeightRow;
    use dpsa_stream::{GapEntry, TotalsReport};

    fn map(rows: &[i64]) -> HeightMap {
        let mut m = HeightMap::new(1, 0.25);
        for &r in rows {
            m.rows.push(HeightRow {
                row: r,
                latch: 0,
                flags: 0,
                heights: vec![0],
                valid: vec![true],
            });
        }
        m
    }

    fn totals(first: i64, last: i64) -> Option<TotalsReport> {
        Some(TotalsReport {
            packets: 0,
            rows: 0,
            gap_rows: 0,
            first_row: first,
            last_row: last,
        })
    }

    #[test]
    fn lost_rows_are_the_uncovered_rows_of_the_span() {
        let mut rep = DecodeReport::default();
        rep.stream.end_totals = totals(10, 30);
        rep.stream.gaps.push(GapEntry {
            first: 20,
            count: 3,
            flags: 0,
        });
        // Rows 10..=14, gap 20..=22, rows 25..=28: lost 15..=19, 23..=24, 29..=30.
        let rows: Vec<i64> = (10..=14).chain(25..=28).collect();
        let (clipped, count, listed) = lost_rows(&map(&rows), &rep, (0, 100));
        assert_eq!(count, 5 + 2 + 2);
        assert_eq!(listed, vec![[15, 19], [23, 24], [29, 30]]);
        assert_eq!(clipped, vec![(15, 19), (23, 24), (29, 30)]);
        // Clipped to where the camera sees the board; the count stays complete.
        let (clipped, count, _) = lost_rows(&map(&rows), &rep, (17, 23));
        assert_eq!(count, 9);
        assert_eq!(clipped, vec![(17, 19), (23, 23)]);
        // A clean stream loses nothing.
        let all: Vec<i64> = (10..=30).collect();
        let mut clean = DecodeReport::default();
        clean.stream.end_totals = totals(10, 30);
        assert_eq!(lost_rows(&map(&all), &clean, (0, 100)).1, 0);
    }

    #[test]
    fn a_stream_without_its_end_is_lost_to_the_end_of_the_board() {
        let rep = DecodeReport::default(); // no end packet
        let (clipped, count, _) = lost_rows(&map(&[5, 6, 7]), &rep, (0, 20));
        // Rows 0..=4 and 8..=20 were never seen.
        assert_eq!(clipped, vec![(0, 4), (8, 20)]);
        assert_eq!(count, 5 + 13);
        // Hostile totals do not overflow: the count saturates, the ranges stay clipped.
        let mut wild = DecodeReport::default();
        wild.stream.end_totals = totals(i64::MIN, i64::MAX);
        let (clipped, count, _) = lost_rows(&map(&[0]), &wild, (-3, 3));
        assert_eq!(clipped, vec![(-3, -1), (1, 3)]);
        assert_eq!(count, u64::MAX);
    }
}
