//! One board map from the cameras' wrapped rows, band of board rows by band as the rows
//! arrive ([`Stitcher`]): each camera's rows unwrapped chunk by chunk
//! ([`crate::unwrap::Unwrapper`]) in a thread of its own, beside a band of board rows
//! resampled from every camera once its rows are unwrapped ([`crate::resample`]), then
//! blended ([`crate::blend::Blender`]) and copied into the map in a thread of its own
//! (`Blending`) while the next band is resampled; then the camera rows no later band needs
//! are dropped. What it holds besides the map: per camera a chunk of wrapped rows with its
//! margins (and at most 2 chunks' rows waiting for its thread), the unwrapped rows of a band, the
//! layers of up to three bands (the one blended, one waiting for the blend, the one
//! resampled; more only while a turn waits for evidence, see [`crate::blend`]).
//! [`assemble`] feeds whole cameras through it.
//!
//! The unwrapping threads and the blend thread keep the cores busy while a band's
//! single-threaded parts run (the blend's turn and seam sums, the copies into the map): with
//! the rows at the conveyor's pace the unwrapping keeps up with them, and a blend on the
//! resampling's thread left a core idle. A chunk's heights do not depend on when it is
//! unwrapped and the bands are blended in their order, so the map is the same bit for bit.

use crate::blend::{Blended, Blender};
use crate::places::RowPlaces;
use crate::resample::{resample, BoardGrid, CameraPlacement, Layer, Source};
use crate::unwrap::{Unwrapper, BLOCK, CHUNK_ROWS, MARGIN_ROWS};
use crate::Grid;
use std::ops::Range;
use std::time::Instant;

/// One camera's measurement, ready for the board.
#[derive(Clone, Debug)]
pub struct CameraRows {
    /// Wrapped heights, um, in `[-T(c)/2, T(c)/2)` (NaN invalid); row `i` is board row
    /// `first_row + i`.
    pub heights: Grid,
    /// Cramer-Rao bound of each height's variance, um^2 (same layout; None without a truth
    /// and noise model).
    pub variance: Option<Grid>,
    /// Pixels masked for the calibration's dead image pixels (`dpsa_sim::board::provenance`).
    pub dead_masked: u64,
    /// Where each row was seen (`dpsa_sim::board::provenance::row_places`; `None`: nominal).
    pub places: Option<RowPlaces>,
    /// The board row of `heights`' row 0 (the core's board-row numbering).
    pub first_row: i64,
    /// Height per turn of each column, um.
    pub period_um: Vec<f32>,
    /// The core's reference phase of each column, rad: with the rows' sample places
    /// ([`RowPlaces::samples`]) each pixel's own place is taken out of its height
    /// ([`crate::places`]); empty: not.
    pub reference_rad: Vec<f32>,
    /// Where the camera's pixels lie on the board (its lateral calibration).
    pub placement: CameraPlacement,
    /// Rows of `heights` that never arrived (a stream's missing or damaged packets, its
    /// truncated end): their board pixels stay invalid. Empty when none was lost.
    pub lost: Vec<bool>,
}

/// Seconds per stage (`timing.*` of `dpsa board --json`), summed over the bands.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Timing {
    /// Waiting for the cameras' unwrapping, s: each camera unwraps in a thread of its own
    /// beside the resampling and blending, so this is the time the bands waited for it, not
    /// the unwrapping's own.
    pub unwrap_s: f64,
    /// Resampling onto the board grid, all cameras (in parallel threads), s.
    pub resample_s: f64,
    /// Blending, turn alignment, seams and the copies into the map, s: the blend thread's
    /// own time, beside the resampling of the next band (it overlaps `resample_s`).
    pub blend_s: f64,
}

/// The assembled map and what it took.
#[derive(Clone, Debug)]
pub struct Assembled {
    /// The board map, the camera of each pixel, the turns and seams.
    pub blended: Blended,
    /// Valid pixels that the unwrapping placed from an extrapolated surface, per camera.
    pub unreached: Vec<usize>,
    /// Board pixels left invalid because a camera lost the rows that would have covered them
    /// (no other camera did).
    pub lost_pixels: u64,
    /// Seconds per stage.
    pub timing: Timing,
}

/// Feather width of the overlaps, camera columns.
pub const FEATHER_PX: f64 = 16.0;

/// Board-edge band that anchors the board's turn, px of the board grid.
pub const EDGE_PX: usize = 8;

/// Board rows per band.
pub const BAND_ROWS: usize = 256;

/// What a [`Stitcher`] knows of a camera before its rows arrive.
#[derive(Clone, Debug)]
pub struct CameraFeed {
    /// The board row of the camera's row 0.
    pub first_row: i64,
    /// Height per turn of each column, um.
    pub period_um: Vec<f32>,
    /// The core's reference phase of each column, rad (see [`CameraRows::reference_rad`]).
    pub reference_rad: Vec<f32>,
    /// Where the camera's pixels lie on the board.
    pub placement: CameraPlacement,
    /// Where each of its rows was seen (`None`: nominal).
    pub places: Option<RowPlaces>,
    /// Rows that never arrived, per camera row (empty: none).
    pub lost: Vec<bool>,
    /// Whether its rows come with a variance.
    pub variance: bool,
}

/// A camera's unwrapping in a thread of its own ([`Unwrapping`]), beside the resampling and
/// blending of the bands whose rows are in: rows go to it as they are pushed and their
/// chunks come back unwrapped (each chunk is the same whenever it is unwrapped, see
/// [`Unwrapper`]).
struct Unwrapping {
    /// Rows to the thread (`None`: the camera ended).
    to: Option<std::sync::mpsc::Sender<Vec<f32>>>,
    /// The values sent and not yet taken by the thread, bounded, so that a thread behind the
    /// rows holds the pusher back rather than a copy of every row.
    queued: std::sync::Arc<Queued>,
    /// That bound, values: [`QUEUED_CHUNKS`] chunks' rows.
    bound: usize,
    /// The thread's unwrapper once it has handed on its last row.
    done: Option<Unwrapper>,
}

/// Values sent to a camera's unwrapping thread and not yet taken ([`Unwrapping::queued`]),
/// and whether the thread has ended.
#[derive(Default)]
struct Queued {
    state: std::sync::Mutex<(usize, bool)>,
    taken: std::sync::Condvar,
}

impl Queued {
    /// Waits until `n` more values fit under `bound` (or nothing is queued: a push larger
    /// than the bound goes alone; or the thread has ended), then counts them in.
    fn add(&self, n: usize, bound: usize) {
        let mut q = self.state.lock().unwrap_or_else(|e| e.into_inner());
        while !q.1 && q.0 > 0 && q.0 + n > bound {
            q = self.taken.wait(q).unwrap_or_else(|e| e.into_inner());
        }
        q.0 += n;
    }

    /// `n` values taken by the thread.
    fn take(&self, n: usize) {
        let mut q = self.state.lock().unwrap_or_else(|e| e.into_inner());
        q.0 = q.0.saturating_sub(n);
        self.taken.notify_all();
    }
}

/// Marks the thread ended when it ends, however it ends (a panic too): a pusher waiting for
/// room then goes on, and its send fails.
struct EndedOnExit(std::sync::Arc<Queued>);

impl Drop for EndedOnExit {
    fn drop(&mut self) {
        let mut q = self.0.state.lock().unwrap_or_else(|e| e.into_inner());
        q.1 = true;
        self.0.taken.notify_all();
    }
}

/// What a camera's unwrapping thread sends back: a chunk of unwrapped rows, or at its end
/// its unwrapper (with its counts).
enum Unwrapped {
    Rows(usize, Grid),
    Done(usize, Box<Unwrapper>),
}

/// Chunks' rows ([`CHUNK_ROWS`]) a camera's thread holds queued before the pusher waits for
/// it, whatever the pushes' sizes: in the line a push is 128 rows, and a bound of 2 pushes
/// held the pusher (and the bands) while the thread unwrapped a chunk; offline a push is a
/// chunk, and 16 of them took `dpsa board`'s peak over 512 MB.
const QUEUED_CHUNKS: usize = 2;

/// A camera's state in the stitching.
struct Cam {
    feed: CameraFeed,
    unwrapping: Unwrapping,
    /// Unwrapped rows held, camera row `held0` first (up to the rows handed on); those from
    /// `settle.settled` on not yet settled ([`crate::places::Settle`]).
    held: Grid,
    settle: crate::places::Settle,
    /// Variance rows from camera row `held0` (as many as pushed).
    variance: Option<Grid>,
    held0: usize,
    ended: bool,
}

impl Cam {
    /// The camera rows that board rows `rows` need (for the resampling's footprint and
    /// bilinear neighbours), from row 0 on.
    fn needs(&self, rows: &Range<usize>, grid: &BoardGrid) -> Range<usize> {
        let (p, w) = (&self.feed.placement, self.feed.period_um.len() as f64);
        if rows.is_empty() || w == 0.0 {
            return 0..0;
        }
        let (sin, _) = p.rotation_rad.sin_cos();
        let xs = [grid.centre(rows.start, 0).0, grid.centre(rows.end - 1, 0).0];
        let mut t = (f64::INFINITY, f64::NEG_INFINITY);
        for x in xs {
            for c in [-1.0, w] {
                let b =
                    (x - p.x0_mm - c * p.pitch_mm * sin) / p.row_mm - self.feed.first_row as f64;
                t = (t.0.min(b), t.1.max(b));
            }
        }
        if !(t.0.is_finite() && t.1.is_finite()) {
            return 0..0;
        }
        // Through the places (increasing) where the rows were seen, else nominal; two rows
        // more either way.
        let (lo, hi) = match &self.feed.places {
            Some(pl) => (
                pl.along
                    .partition_point(|&a| a < t.0 - 2.0)
                    .saturating_sub(1),
                pl.along.partition_point(|&a| a <= t.1 + 2.0) + 1,
            ),
            None => {
                let lo = (t.0 - 2.0).floor().max(0.0) as usize;
                (lo, ((t.1 + 3.0).ceil().max(0.0) as usize).max(lo))
            }
        };
        lo..hi
    }

    /// Whether the camera ended and every row it pushed came back unwrapped.
    fn all_unwrapped(&self) -> bool {
        self.ended && self.unwrapping.done.is_some()
    }

    /// Whether the rows `need` are all unwrapped and settled (or will never come).
    fn has(&self, need: &Range<usize>) -> bool {
        let done = self.settle.settled;
        need.end <= done || (self.all_unwrapped() && done == self.held0 + self.held.rows)
    }

    /// Takes each pixel's own place out of the rows unwrapped so far (see [`crate::places`]).
    fn settle(&mut self) {
        let last_known = self.all_unwrapped();
        self.settle.rows(
            &mut self.held,
            self.held0,
            self.feed.places.as_ref(),
            &self.feed.reference_rad,
            &self.feed.period_um,
            last_known,
        );
    }

    /// Drops the held rows before camera row `row`, once they are at least as many as the
    /// rows kept (each row is then moved about once, not once per band; at most twice the
    /// rows needed are held).
    fn drop_before(&mut self, row: usize) {
        let w = self.held.width;
        let row = row.min(self.settle.settled);
        let k = row.saturating_sub(self.held0).min(self.held.rows);
        if k == 0 || 2 * k < self.held.rows {
            return;
        }
        self.held.data.drain(..k * w);
        self.held.rows -= k;
        if let Some(v) = &mut self.variance {
            let kv = k.min(v.rows);
            v.data.drain(..kv * w);
            v.rows -= kv;
        }
        self.held0 += k;
    }
}

/// The board map built band by band as the cameras' rows arrive (see the module docs).
pub struct Stitcher {
    grid: BoardGrid,
    cams: Vec<Cam>,
    blending: Blending,
    band_rows: usize,
    /// The first board row not yet resampled.
    next: usize,
    /// Height values [`Self::push`] did not take (see [`Self::refused_values`]).
    refused: usize,
    timing: Timing,
    /// The cameras' unwrapping threads' chunks.
    unwrapped: std::sync::mpsc::Receiver<Unwrapped>,
}

impl Stitcher {
    /// A map on `grid` from `cams` (in order across the board), `band_rows` board rows per
    /// band and camera chunks of `chunk_rows` ([`BAND_ROWS`], [`CHUNK_ROWS`]).
    pub fn new(
        grid: BoardGrid,
        cams: Vec<CameraFeed>,
        band_rows: usize,
        chunk_rows: usize,
    ) -> Stitcher {
        let variance = cams.iter().any(|c| c.variance);
        let n = cams.len();
        let (back, unwrapped) = std::sync::mpsc::channel();
        let cams = cams
            .into_iter()
            .enumerate()
            .map(|(k, feed)| {
                let w = feed.period_um.len();
                let unwrapper =
                    Unwrapper::new(feed.period_um.clone(), BLOCK, chunk_rows, MARGIN_ROWS);
                Cam {
                    unwrapping: unwrapping(
                        k,
                        unwrapper,
                        back.clone(),
                        QUEUED_CHUNKS * chunk_rows.max(1) * w.max(1),
                    ),
                    // The held rows of a stitcher before, given back at its `finish` when the
                    // pools are kept between boards.
                    held: Grid {
                        width: w,
                        rows: 0,
                        data: crate::pool::HELD.take_empty(0),
                    },
                    settle: crate::places::Settle::default(),
                    variance: feed.variance.then(|| Grid::invalid(w, 0)),
                    held0: 0,
                    ended: false,
                    feed,
                }
            })
            .collect();
        Stitcher {
            grid,
            cams,
            blending: Blending::new(MapRows::new(grid, variance), Blender::new(grid, n, EDGE_PX)),
            band_rows: band_rows.max(1),
            next: 0,
            refused: 0,
            timing: Timing::default(),
            unwrapped,
        }
    }

    /// Takes the paste's reflectance out of every camera's walls from now on (see
    /// [`crate::places::PasteReflectance`]; the default takes nothing out). Set before the first
    /// push: rows already settled keep what they had.
    pub fn set_paste(&mut self, paste: crate::places::PasteReflectance) {
        for c in &mut self.cams {
            c.settle.paste = paste;
        }
    }

    /// Board rows of the map finished so far (from row 0).
    pub fn rows_done(&self) -> usize {
        self.blending
            .done
            .load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Height values [`Self::push`] did not take: rows of a camera after its [`Self::end`],
    /// and a part row at the end of a push. Neither `dpsa board --streams` nor the line
    /// pushes any; a count above 0 is a caller's mistake, which the caller can see here
    /// (debug builds stop at [`Self::finish`]).
    pub fn refused_values(&self) -> usize {
        self.refused
    }

    /// Camera `cam`'s next rows: wrapped heights (whole rows, um, NaN invalid) and, when the
    /// camera has one, their variance (um^2, same layout). Call [`Self::advance`] to work on
    /// them.
    /// A camera with a variance whose rows come without one has it unknown (NaN) there.
    /// Whole rows only: a part row at the end, and rows after [`Self::end`] of that camera,
    /// are not taken but counted ([`Self::refused_values`]).
    pub fn push(&mut self, cam: usize, heights: &[f32], variance: Option<&[f32]>) {
        let c = &mut self.cams[cam];
        let w = c.feed.period_um.len().max(1);
        let rows = if c.ended { 0 } else { heights.len() / w };
        self.refused += heights.len() - rows * w;
        match &c.unwrapping.to {
            Some(to) if rows > 0 => {
                // Waits while the thread is behind by the bound.
                c.unwrapping.queued.add(rows * w, c.unwrapping.bound);
                // The thread ends only when told or when the stitcher is dropped. It gives
                // the rows back once it has them (`pool::give_rows`).
                let mut v = crate::pool::ROWS.take_empty(rows * w);
                v.extend_from_slice(&heights[..rows * w]);
                let _ = to.send(v);
            }
            _ => return,
        }
        if let Some(v) = c.variance.as_mut() {
            // Row for row with the heights taken.
            let n = rows * v.width;
            match variance {
                Some(rows) if rows.len() >= n => v.data.extend_from_slice(&rows[..n]),
                _ => v.data.resize(v.data.len() + n, f32::NAN),
            }
            v.rows = v.data.len() / v.width.max(1);
        }
    }

    /// Where camera `cam`'s next rows were seen: `places` of rows from board row `first_row`
    /// (their `along` from that row), appended to the camera's (from its first row). Call it
    /// with [`Self::push`] of the same rows, before [`Self::advance`].
    pub fn push_places(&mut self, cam: usize, places: &RowPlaces, first_row: i64) {
        let feed = &mut self.cams[cam].feed;
        let offset = (first_row - feed.first_row) as f64;
        let pl = feed.places.get_or_insert_with(|| RowPlaces {
            along: Vec::new(),
            across: Vec::new(),
            samples: Vec::new(),
        });
        // Rows without sample places (none given) are seen at their row's place.
        pl.samples.resize(pl.along.len(), Default::default());
        pl.along.extend(places.along.iter().map(|a| a + offset));
        pl.across.extend_from_slice(&places.across);
        pl.samples.extend_from_slice(&places.samples);
    }

    /// No more rows come from camera `cam`.
    pub fn end(&mut self, cam: usize) {
        let c = &mut self.cams[cam];
        c.ended = true;
        // The thread unwraps what it holds and hands on its unwrapper.
        c.unwrapping.to = None;
    }

    /// Takes the unwrapped chunks that came back into the cameras' held rows (waiting for one
    /// when `wait` and a camera still unwraps), and settles them; returns whether any came.
    fn take_unwrapped(&mut self, wait: bool) -> bool {
        let mut any = false;
        loop {
            let pending = self.cams.iter().any(|c| c.unwrapping.done.is_none());
            let got = if wait && !any && pending {
                match self.unwrapped.recv() {
                    Ok(m) => Some(m),
                    // Every thread is gone and one never sent its last rows: it panicked (a
                    // bug). Stop, as the threads did when the stitcher ran them in a scope,
                    // rather than wait for rows that cannot come.
                    Err(_) => panic!("a camera's unwrapping thread stopped before its last rows"),
                }
            } else {
                self.unwrapped.try_recv().ok()
            };
            let Some(msg) = got else { break };
            any = true;
            match msg {
                Unwrapped::Rows(k, g) => {
                    let c = &mut self.cams[k];
                    c.held.data.extend_from_slice(&g.data);
                    c.held.rows += g.rows;
                    crate::pool::give_rows(g.data);
                }
                Unwrapped::Done(k, u) => self.cams[k].unwrapping.done = Some(*u),
            }
        }
        for c in &mut self.cams {
            c.settle();
        }
        any
    }

    /// Unwraps what has arrived and builds every band whose rows are unwrapped.
    pub fn advance(&mut self) {
        let t0 = Instant::now();
        self.take_unwrapped(false);
        self.timing.unwrap_s += t0.elapsed().as_secs_f64();
        self.build_bands();
    }

    /// Builds every band whose rows are unwrapped, in order.
    fn build_bands(&mut self) {
        while self.next < self.grid.rows {
            let band = self.next..(self.next + self.band_rows).min(self.grid.rows);
            let halo = Blender::halo_of(&self.grid, &band);
            let grid = &self.grid;
            if !self.cams.iter().all(|c| c.has(&c.needs(&halo, grid))) {
                break;
            }
            let t1 = Instant::now();
            let layers: Vec<Layer> = std::thread::scope(|s| {
                let handles: Vec<_> = self
                    .cams
                    .iter()
                    .map(|c| {
                        let halo = halo.clone();
                        s.spawn(move || {
                            let src = Source {
                                heights: &c.held,
                                row0: c.held0,
                                variance: c.variance.as_ref(),
                                period_um: &c.feed.period_um,
                                first_row: c.feed.first_row,
                                places: c.feed.places.as_ref(),
                                lost_rows: &c.feed.lost,
                            };
                            resample(&src, &c.feed.placement, grid, halo, FEATHER_PX)
                        })
                    })
                    .collect();
                handles
                    .into_iter()
                    .map(|h| h.join().expect("resample thread"))
                    .collect()
            });
            self.timing.resample_s += t1.elapsed().as_secs_f64();
            self.next = band.end;
            // The blend thread takes it once it has blended the band before (the resampling
            // of the next band goes on meanwhile).
            self.blending.band(band, layers);
            // The next band's halo starts one row before it.
            let next = Blender::halo_of(&self.grid, &(self.next..self.next + 1));
            for c in &mut self.cams {
                let from = c.needs(&next, &self.grid).start;
                c.drop_before(from);
            }
        }
    }

    /// Ends every camera, builds the remaining bands and returns the map.
    pub fn finish(mut self) -> Assembled {
        debug_assert_eq!(
            self.refused, 0,
            "rows pushed after a camera's end, or part rows"
        );
        for k in 0..self.cams.len() {
            self.end(k);
        }
        // Bands as the last chunks come back.
        loop {
            let t0 = Instant::now();
            let came = self.take_unwrapped(true);
            self.timing.unwrap_s += t0.elapsed().as_secs_f64();
            self.build_bands();
            if !came && self.cams.iter().all(|c| c.unwrapping.done.is_some()) {
                break;
            }
        }
        let unreached = self
            .cams
            .iter()
            .map(|c| c.unwrapping.done.as_ref().map_or(0, |u| u.unreached))
            .collect();
        let (map, blender, blend_s) = self.blending.finish();
        for c in &mut self.cams {
            crate::pool::HELD.give_kept(std::mem::take(&mut c.held.data));
        }
        let (turns, edge_median_um, edge_off_bands, seams) = blender.finish();
        let (w, rows) = (self.grid.width, self.grid.rows);
        let grid = |data: Vec<f32>| Grid {
            width: w,
            rows,
            data,
        };
        self.timing.blend_s = blend_s;
        Assembled {
            blended: Blended {
                heights: grid(map.heights),
                variance: map.variance.map(grid),
                camera: map.camera,
                turns,
                edge_median_um,
                edge_off_bands,
                seams,
            },
            unreached,
            lost_pixels: map.lost_pixels,
            timing: self.timing,
        }
    }
}

/// The map's rows so far (grown band by band: no page of the map is touched before its band
/// is blended).
struct MapRows {
    heights: Vec<f32>,
    variance: Option<Vec<f32>>,
    camera: Vec<u8>,
    lost_pixels: u64,
}

impl MapRows {
    fn new(grid: BoardGrid, variance: bool) -> MapRows {
        // Buffers a finished map gave back when the pools are kept between boards
        // (`pool::keep_between_boards`), else new ones.
        let n = grid.rows * grid.width;
        MapRows {
            heights: crate::pool::MAP_F32.take_empty(n),
            variance: variance.then(|| crate::pool::MAP_F32.take_empty(n)),
            camera: crate::pool::MAP_U8.take_empty(n),
            lost_pixels: 0,
        }
    }

    /// Appends blended bands (in board-row order); returns the board row after the last.
    fn put(&mut self, bands: Vec<crate::blend::BandMap>, mut done: usize) -> usize {
        for m in bands {
            debug_assert_eq!(m.rows.start, done, "bands in order");
            self.heights.extend_from_slice(m.heights());
            self.camera.extend_from_slice(m.camera());
            if let Some(v) = self.variance.as_mut() {
                match m.variance() {
                    Some(mv) => v.extend_from_slice(mv),
                    None => v.resize(self.heights.len(), f32::NAN),
                }
            }
            self.lost_pixels += m.lost_pixels;
            done = m.rows.end;
            crate::blend::recycle(m);
        }
        done
    }
}

/// What the blend thread is handed.
enum ToBlend {
    /// A band's rows and every camera's layer over its halo.
    Band(Range<usize>, Vec<Layer>),
    /// No more bands: blend those waiting and hand back the map.
    Finish,
}

/// The blend and the map in a thread of their own, a band behind the resampling: the blend of
/// a band (single-threaded: the turns, the seams' sums, the copies into the map) runs while
/// the next band is resampled, so that a core is not left idle through it when the
/// unwrapping has caught up with the rows (as in the line, where the rows come at the
/// conveyor's pace). At most one band waits for it; the bands are blended in their order, so
/// the map is the same bit for bit.
struct Blending {
    to: std::sync::mpsc::SyncSender<ToBlend>,
    /// The map, the blender and the seconds it blended, at the end.
    thread: std::thread::JoinHandle<Option<(MapRows, Blender, f64)>>,
    /// Board rows in the map so far.
    done: std::sync::Arc<std::sync::atomic::AtomicUsize>,
}

impl Blending {
    fn new(mut map: MapRows, mut blender: Blender) -> Blending {
        let (to, bands) = std::sync::mpsc::sync_channel::<ToBlend>(1);
        let done = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let rows = std::sync::Arc::clone(&done);
        let thread = std::thread::spawn(move || {
            let mut seconds = 0.0;
            let mut at = 0;
            // A stitcher dropped before its end (an abandoned board) stops it quietly.
            while let Ok(msg) = bands.recv() {
                let t = Instant::now();
                let finish = matches!(msg, ToBlend::Finish);
                let blended = match msg {
                    ToBlend::Band(band, layers) => blender.band(band, layers),
                    ToBlend::Finish => blender.end(),
                };
                at = map.put(blended, at);
                rows.store(at, std::sync::atomic::Ordering::Relaxed);
                seconds += t.elapsed().as_secs_f64();
                if finish {
                    return Some((map, blender, seconds));
                }
            }
            None
        });
        Blending { to, thread, done }
    }

    /// Hands on band `rows` with every camera's layer over its halo (waiting while the band
    /// before is blended).
    fn band(&self, rows: Range<usize>, layers: Vec<Layer>) {
        if self.to.send(ToBlend::Band(rows, layers)).is_err() {
            // The thread ends only when told or when the stitcher is dropped: it panicked (a
            // bug), as an unwrapping thread that never sends its last rows.
            panic!("the blend thread stopped before the map's end");
        }
    }

    /// Blends the bands waiting and hands back the map, the blender and the seconds blended.
    fn finish(self) -> (MapRows, Blender, f64) {
        let _ = self.to.send(ToBlend::Finish);
        match self.thread.join() {
            Ok(Some(r)) => r,
            _ => panic!("the blend thread stopped before the map's end"),
        }
    }
}

/// Camera `k`'s unwrapping thread: it unwraps every chunk `unwrapper` has the rows for as
/// they come, sends them `back`, and at the camera's end (its sender dropped) the last chunks
/// and the unwrapper. It stops early, quietly, when the stitcher is gone.
fn unwrapping(
    k: usize,
    mut unwrapper: Unwrapper,
    back: std::sync::mpsc::Sender<Unwrapped>,
    bound: usize,
) -> Unwrapping {
    let (to, rows) = std::sync::mpsc::channel::<Vec<f32>>();
    let queued = std::sync::Arc::new(Queued::default());
    let on_exit = EndedOnExit(std::sync::Arc::clone(&queued));
    std::thread::spawn(move || {
        let on_exit = on_exit;
        let mut ended = false;
        loop {
            while let Some(g) = unwrapper.next(ended) {
                if back.send(Unwrapped::Rows(k, g)).is_err() {
                    return;
                }
            }
            if ended {
                let _ = back.send(Unwrapped::Done(k, Box::new(unwrapper)));
                return;
            }
            match rows.recv() {
                Ok(r) => {
                    unwrapper.push(&r);
                    on_exit.0.take(r.len());
                    crate::pool::give_rows(r);
                }
                Err(_) => ended = true,
            }
        }
    });
    Unwrapping {
        to: Some(to),
        queued,
        bound,
        done: None,
    }
}

/// Unwraps, resamples and blends `cameras` (in order across the board) onto `grid` through a
/// [`Stitcher`], fed a chunk of every camera's rows at a time.
/// The paste's reflectance is taken out of the walls with `paste`
/// ([`Stitcher::set_paste`]).
pub fn assemble(
    cameras: Vec<CameraRows>,
    grid: &BoardGrid,
    paste: crate::places::PasteReflectance,
) -> Assembled {
    assemble_in(cameras, grid, BAND_ROWS, CHUNK_ROWS, paste)
}

/// What the stitcher needs of a camera before its rows.
fn feed_of(c: &CameraRows) -> CameraFeed {
    CameraFeed {
        first_row: c.first_row,
        period_um: c.period_um.clone(),
        reference_rad: c.reference_rad.clone(),
        placement: c.placement,
        places: c.places.clone(),
        lost: c.lost.clone(),
        variance: c.variance.is_some(),
    }
}

/// [`assemble`] with `band_rows` board rows per band and camera chunks of `chunk_rows`.
pub fn assemble_in(
    cameras: Vec<CameraRows>,
    grid: &BoardGrid,
    band_rows: usize,
    chunk_rows: usize,
    paste: crate::places::PasteReflectance,
) -> Assembled {
    let feeds = cameras.iter().map(feed_of).collect();
    // Each camera's rows cut into chunks, one camera at a time, so that every chunk is freed
    // once pushed (a camera's grid cannot give back its first rows).
    let step = chunk_rows.max(1);
    let split = |g: Grid| -> std::collections::VecDeque<Vec<f32>> {
        g.data
            .chunks(step * g.width.max(1))
            .map(<[f32]>::to_vec)
            .collect()
    };
    let mut chunks: Vec<_> = cameras
        .into_iter()
        .map(|c| (split(c.heights), c.variance.map(split)))
        .collect();
    let mut st = Stitcher::new(*grid, feeds, band_rows, chunk_rows);
    st.set_paste(paste);
    while chunks.iter().any(|c| !c.0.is_empty()) {
        for (k, (h, v)) in chunks.iter_mut().enumerate() {
            let Some(rows) = h.pop_front() else {
                st.end(k);
                continue;
            };
            let var = v.as_mut().and_then(|v| v.pop_front());
            st.push(k, &rows, var.as_deref());
        }
        st.advance();
    }
    st.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bound on what waits for an unwrapping thread: a push that would pass it waits
    /// until the thread has taken enough, a push larger than the bound goes alone, and a
    /// thread that ended (however) never holds a pusher.
    #[test]
    fn a_push_waits_for_room_and_never_for_an_ended_thread() {
        use std::sync::atomic::{AtomicBool, Ordering::SeqCst};
        use std::sync::Arc;
        let q = Arc::new(Queued::default());
        q.add(6, 10);
        let pushed = Arc::new(AtomicBool::new(false));
        let pusher = {
            let (q, pushed) = (Arc::clone(&q), Arc::clone(&pushed));
            std::thread::spawn(move || {
                q.add(6, 10);
                pushed.store(true, SeqCst);
            })
        };
        std::thread::sleep(std::time::Duration::from_millis(100));
        assert!(!pushed.load(SeqCst), "6 + 6 values went past a bound of 10");
        q.take(6);
        pusher.join().unwrap();
        assert!(pushed.load(SeqCst));
        // Alone, a push of more than the bound goes.
        q.take(6);
        q.add(25, 10);
        // 25 wait; the thread ends without taking them: the next push does not wait.
        let pusher = {
            let q = Arc::clone(&q);
            std::thread::spawn(move || q.add(5, 10))
        };
        drop(EndedOnExit(Arc::clone(&q)));
        pusher.join().unwrap();
    }

    /// The truth: a bow of 2 turns (no chunk's seed block on turn 0), 0 at the edges and flat
    /// at the side edges, and paste boxes with sloped walls, um at board `(x, y)` mm. The
    /// board is 20 times narrower than a real one, its slopes 10 times steeper (up to 8 um
    /// per pixel).
    fn truth(x: f64, y: f64, len: f64, wid: f64) -> f64 {
        let (xi, eta) = (2.0 * x / len - 1.0, 2.0 * y / wid - 1.0);
        let across = (1.0 - eta * eta).powi(2);
        let bow = 300.0 * (1.0 - xi * xi) * across;
        let tilt = 500.0 * (std::f64::consts::PI * x / len).sin() * across;
        let (u, v) = (x.rem_euclid(1.0), y.rem_euclid(1.0));
        let inside = (u - 0.1).min(0.5 - u).min(v - 0.1).min(0.6 - v);
        bow + tilt + 120.0 * (inside / 0.1 + 0.5).clamp(0.0, 1.0)
    }

    const LEN: f64 = 36.0;
    const WID: f64 = 9.0;
    const T_UM: f32 = 400.0;

    /// Three cameras of 120 columns across the board, rotated, wrapped; camera 1 seen at
    /// places off its nominal rows, camera 2 with 40 lost rows.
    fn cameras() -> (Vec<CameraRows>, BoardGrid) {
        cameras_over(|x, y| truth(x, y, LEN, WID))
    }

    /// [`cameras`] over the heights `truth` (um at board `(x, y)` mm).
    fn cameras_over(truth: impl Fn(f64, f64) -> f64) -> (Vec<CameraRows>, BoardGrid) {
        let rows = 1200usize;
        let cams = [0.0, 2.95, 5.9]
            .into_iter()
            .enumerate()
            .map(|(k, y0)| {
                let place = CameraPlacement {
                    x0_mm: 0.0,
                    y0_mm: y0,
                    row_mm: 0.03,
                    pitch_mm: 0.0301,
                    rotation_rad: [0.002, -0.003, 0.001][k],
                };
                let w = 104usize;
                let period: Vec<f32> = (0..w)
                    .map(|c| T_UM * (1.0 + 0.02 * (c as f32 / w as f32 - 0.5)))
                    .collect();
                let along: Vec<f64> = (0..rows)
                    .map(|i| i as f64 + 0.3 * (i as f64 / 17.0).sin())
                    .collect();
                let mut g = Grid::invalid(w, rows);
                for (b, &seen) in along.iter().enumerate() {
                    for (c, &t) in period.iter().enumerate() {
                        let row = if k == 1 { seen } else { b as f64 };
                        let (x, y) = place.to_board(row, c as f64);
                        let h = truth(x, y) as f32;
                        *g.at_mut(b, c) = h - t * (h / t + 0.5).floor();
                    }
                }
                let mut lost = Vec::new();
                if k == 2 {
                    lost = vec![false; rows];
                    lost[700..740].fill(true);
                    for r in 700..740 {
                        g.data[r * w..(r + 1) * w].fill(f32::NAN);
                    }
                }
                CameraRows {
                    heights: g,
                    variance: None,
                    dead_masked: 0,
                    places: (k == 1).then(|| RowPlaces {
                        along,
                        across: vec![0.0; rows],
                        samples: Vec::new(),
                    }),
                    first_row: 0,
                    period_um: period,
                    reference_rad: Vec::new(),
                    placement: place,
                    lost,
                }
            })
            .collect();
        let grid = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.03,
            rows: 1200,
            width: 300,
        };
        (cams, grid)
    }

    #[test]
    fn band_by_band_the_map_is_the_truth_whatever_the_band() {
        let (cams, grid) = cameras();
        let whole = assemble_in(cams.clone(), &grid, grid.rows, 5000, Default::default());
        let m = &whole.blended;
        // Absolute heights: no pixel a turn off, the median error small.
        let mut errs = Vec::new();
        for i in 0..grid.rows {
            for j in 0..grid.width {
                let h = m.heights.at(i, j);
                if h.is_finite() {
                    let (x, y) = grid.centre(i, j);
                    errs.push((f64::from(h) - truth(x, y, LEN, WID)).abs());
                }
            }
        }
        errs.sort_by(f64::total_cmp);
        assert!(
            errs.len() > grid.rows * grid.width * 85 / 100,
            "{}",
            errs.len()
        );
        assert!(
            errs[errs.len() / 2] < 1.0,
            "median {}",
            errs[errs.len() / 2]
        );
        assert!(errs[errs.len() - 1] < 100.0, "max {}", errs[errs.len() - 1]);
        assert!(whole.lost_pixels > 0 && m.off_turn_bands() == 0);
        // The same map band by band and chunk by chunk, as rows arrive.
        for (band, chunk) in [(37, 64), (256, 100), (1, 512)] {
            let a = assemble_in(cams.clone(), &grid, band, chunk, Default::default());
            let b = &a.blended;
            // (The turns each camera was moved by depend on its first chunk's seed block;
            // the heights they give do not.)
            assert_eq!(b.camera, m.camera, "band {band}");
            assert_eq!(a.lost_pixels, whole.lost_pixels);
            assert_eq!(
                b.off_turn_bands(),
                0,
                "band {band}: {} {:?}",
                b.edge_off_bands,
                b.seams
            );
            for (x, y) in b.heights.data.iter().zip(&m.heights.data) {
                assert_eq!(x.is_finite(), y.is_finite());
                if x.is_finite() {
                    assert!((x - y).abs() < 1e-3, "band {band}: {x} {y}");
                }
            }
            for (s, t) in b.seams.iter().zip(&m.seams) {
                assert_eq!((s.pixels, s.flat_pixels), (t.pixels, t.flat_pixels));
                let close = |p: Option<f64>, q: Option<f64>| match (p, q) {
                    (Some(p), Some(q)) => (p - q).abs() < 1e-3,
                    (p, q) => p.is_none() && q.is_none(),
                };
                assert!(close(s.height_step_um, t.height_step_um), "{s:?} {t:?}");
                assert!(close(s.shift_x_um, t.shift_x_um) && close(s.shift_y_um, t.shift_y_um));
            }
        }
    }

    /// Rows that come camera by camera in pieces of their own sizes, the stitcher advanced
    /// after every piece (as the line's receivers hand them on), give the map of whole
    /// cameras bit for bit: the cameras' chunks wait for each other to unwrap, and when a
    /// chunk is unwrapped does not change its heights.
    #[test]
    fn rows_in_uneven_pieces_give_the_same_map() {
        let (cams, grid) = cameras();
        let whole = assemble_in(cams.clone(), &grid, 64, 128, Default::default());
        let mut st = Stitcher::new(grid, cams.iter().map(feed_of).collect(), 64, 128);
        let pieces = [100usize, 37, 250];
        let mut at = vec![0usize; cams.len()];
        let mut advances = 0;
        while at.iter().zip(&cams).any(|(a, c)| *a < c.heights.rows) {
            for (k, c) in cams.iter().enumerate() {
                let w = c.heights.width;
                let end = (at[k] + pieces[k]).min(c.heights.rows);
                if at[k] == end {
                    st.end(k);
                    continue;
                }
                let var = c.variance.as_ref().map(|v| &v.data[at[k] * w..end * w]);
                st.push(k, &c.heights.data[at[k] * w..end * w], var);
                at[k] = end;
                if end == c.heights.rows {
                    st.end(k);
                }
                st.advance();
                advances += 1;
            }
        }
        assert!(advances > 10, "{advances}");
        let a = st.finish();
        assert_eq!(a.blended.camera, whole.blended.camera);
        assert_eq!(a.lost_pixels, whole.lost_pixels);
        let bits = |g: &Grid| g.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert!(bits(&a.blended.heights) == bits(&whole.blended.heights));
    }

    /// Board after board with the pools kept (as the line keeps them): a map's memory given
    /// back with stale values in it (here made absurd) serves a later map, which is the
    /// first one's bits. The keeping is the process's from here on: the other tests then run
    /// on kept buffers too, which every buffer's user writes before it reads.
    #[test]
    fn maps_on_memory_given_back_are_the_same_bits() {
        let (cams, grid) = cameras();
        crate::pool::keep_between_boards();
        assert!(crate::pool::kept_between_boards());
        let bits = |g: &Grid| g.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        let first = assemble_in(cams.clone(), &grid, 64, 128, Default::default());
        let want = bits(&first.blended.heights);
        let camera = first.blended.camera.clone();
        for _ in 0..2 {
            let mut old = first.blended.heights.clone();
            old.data.fill(-1.0e30);
            crate::pool::give_map(old);
            crate::pool::give_camera(vec![9; camera.len()]);
            let next = assemble_in(cams.clone(), &grid, 64, 128, Default::default());
            assert!(bits(&next.blended.heights) == want);
            assert_eq!(next.blended.camera, camera);
            crate::pool::give_map(next.blended.heights);
            crate::pool::give_camera(next.blended.camera);
        }
    }

    #[test]
    fn rows_after_a_cameras_end_and_part_rows_are_refused_and_counted() {
        let (cams, grid) = cameras();
        let mut st = Stitcher::new(grid, cams.iter().map(feed_of).collect(), 64, 128);
        let (w, h) = (cams[0].heights.width, &cams[0].heights.data);
        st.push(0, &h[..2 * w], None);
        assert_eq!(st.refused_values(), 0);
        // A part row at a push's end.
        st.push(0, &h[2 * w..3 * w + 3], None);
        assert_eq!(st.refused_values(), 3);
        st.end(0);
        st.push(0, &h[3 * w..5 * w], None);
        assert_eq!(st.refused_values(), 3 + 2 * w);
        // Another camera is not affected.
        st.push(1, &cams[1].heights.data[..cams[1].heights.width], None);
        assert_eq!(st.refused_values(), 3 + 2 * w);
        st.advance();
    }

    #[test]
    fn a_board_whose_trailing_edge_is_a_turn_high_is_flagged() {
        // The same board rising by 1.25 turns towards its trailing edge (not clamped there):
        // the leading edge chooses the board's turn, the last bands' edge pixels disagree.
        let (cams, grid) = cameras_over(|x, y| {
            let eta = 2.0 * y / WID - 1.0;
            truth(x, y, LEN, WID) + 500.0 * x / LEN * (1.0 - eta * eta).powi(2)
        });
        let a = assemble(cams, &grid, Default::default());
        assert!(a.blended.edge_off_bands > 0);
        let (cams, grid) = cameras();
        assert_eq!(
            assemble(cams, &grid, Default::default())
                .blended
                .edge_off_bands,
            0
        );
    }
}
