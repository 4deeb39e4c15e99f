//! The cameras' layers into one board map, band of board rows by band.
//!
//! 1. **Turns between cameras.** Each camera was unwrapped on its own (`super::unwrap`), so
//!    two neighbours may sit whole turns apart. Layers are taken in order across the board;
//!    each is moved by the whole number of turns that brings the median of its difference to
//!    the previous layer, over their shared valid pixels, nearest to zero. The turn is decided
//!    on the first band where the two share at least [`MIN_SHARED`] valid pixels (the board's
//!    leading rows: the first band on the shipped scenes) and held; every later band with as
//!    many is checked against it, and a band whose own median says another turn is counted
//!    ([`Blended::off_turn_bands`]: the map's evidence that a camera's unwrapping slipped).
//! 2. **The board's turn.** The board is clamped at its edges on the conveyor rails, which the
//!    calibration planes define as height 0: the whole map is moved by the whole number of
//!    turns that brings the median height of the valid pixels within `edge_px` of the board
//!    outline nearest to zero. It is decided on the leading edge and the side edges of the
//!    first bands, as soon as [`MIN_EDGE`] edge pixels are valid, and every band's side-edge
//!    pixels and its leading or trailing edge rows are checked against it, each on their own
//!    ([`Blended::edge_off_bands`]).
//!    Bands wait (held whole) until both decisions are made; on a board they are made on its
//!    first band.
//! 3. **Blend.** Each pixel is the weighted mean of the valid layers (weights fall to zero at a
//!    camera's side edges, so overlaps are feathered); the camera with the largest weight is
//!    recorded as the pixel's source.
//! 4. **Seams.** For each pair of neighbouring layers, over their shared valid pixels on flat
//!    board (the 3 x 3 range of the blended map below [`FLAT_RANGE_UM`]): the mean height
//!    difference, and the lateral misregistration: the shift (along and across, sub-pixel, a
//!    gradient estimate without interpolation, see `ShiftSums`) that best aligns one layer to
//!    the other over all shared pixels. The shift needs texture: at least [`MIN_WALL_PIXELS`]
//!    deposit-wall pixels (a step above [`WALL_UM`] between neighbours along the shift) in the
//!    overlap; otherwise it is not reported (null). Both are sums over the pixels, added band
//!    by band: the whole board is their window. A band's layers carry one row of context on
//!    either side (its halo) for the 3 x 3 range and the shift's central differences.

use crate::resample::{BoardGrid, Layer};
use crate::Grid;
use std::collections::VecDeque;
use std::ops::Range;

/// A pixel counts as flat board when the 3 x 3 range of the blended map is below this, um.
pub const FLAT_RANGE_UM: f32 = 25.0;

/// A height step between neighbouring pixels above this is a deposit wall, um.
pub const WALL_UM: f32 = 20.0;
/// Wall pixels a seam's shared area needs for its misregistration to be measured.
pub const MIN_WALL_PIXELS: usize = 50;

/// Shared valid pixels of two neighbouring layers that decide (or check) their turn.
pub const MIN_SHARED: usize = 200;

/// Valid board-edge pixels that decide (or check) the board's turn.
pub const MIN_EDGE: usize = 500;

/// No camera (invalid pixel) in [`Blended::camera`].
pub const NO_CAMERA: u8 = u8::MAX;

/// Two neighbouring cameras over their shared pixels.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Seam {
    /// Layer indices (the earlier, the later).
    pub cameras: (usize, usize),
    /// Shared valid pixels.
    pub pixels: u64,
    /// Of them, on flat board.
    pub flat_pixels: u64,
    /// Mean height of the later minus the earlier over the flat shared pixels, um.
    pub height_step_um: Option<f64>,
    /// Misregistration along the motion (later against earlier), um.
    pub shift_x_um: Option<f64>,
    /// Misregistration across the motion, um.
    pub shift_y_um: Option<f64>,
    /// Bands whose own median difference put the later camera on another turn than the one
    /// held (step 1): 0 on a good map.
    pub off_turn_bands: u64,
}

impl Seam {
    /// Length of the misregistration vector, um.
    pub fn lateral_um(&self) -> Option<f64> {
        Some(self.shift_x_um?.hypot(self.shift_y_um?))
    }
}

/// The blended board map.
#[derive(Clone, Debug)]
pub struct Blended {
    /// Absolute heights, um (NaN invalid).
    pub heights: Grid,
    /// Variance of each height, um^2, through the blending weights (NaN: unknown); `None`
    /// when no camera came with one.
    pub variance: Option<Grid>,
    /// Source camera of each pixel ([`NO_CAMERA`] where invalid).
    pub camera: Vec<u8>,
    /// Whole turns each layer was moved by (steps 1 and 2).
    pub turns: Vec<i32>,
    /// Median height of the board edge pixels that decided the board's turn, before it, um
    /// (None: no valid edge pixel).
    pub edge_median_um: Option<f64>,
    /// Bands whose edge pixels put the board on another turn than the one held (step 2): 0 on
    /// a good map.
    pub edge_off_bands: u64,
    /// Neighbouring layers.
    pub seams: Vec<Seam>,
}

impl Blended {
    /// Bands on another turn than the one held, between cameras or at the board's edge.
    pub fn off_turn_bands(&self) -> u64 {
        self.edge_off_bands + self.seams.iter().map(|s| s.off_turn_bands).sum::<u64>()
    }
}

fn median(mut v: Vec<f32>) -> Option<f32> {
    if v.is_empty() {
        return None;
    }
    let k = v.len() / 2;
    Some(*v.select_nth_unstable_by(k, f32::total_cmp).1)
}

/// One band of the blended map: board rows `rows`, row-major over the grid's width, the
/// values `part` of buffers that hold the band's halo rows too (cutting the band out of them
/// would move the whole band once more, a copy the map's own makes needless).
#[derive(Clone, Debug)]
pub struct BandMap {
    /// Board rows.
    pub rows: Range<usize>,
    /// The band's values in each buffer below (`rows.len() x` the grid's width of them; the
    /// buffers hold the halo rows around them too, so they are read through the accessors).
    part: Range<usize>,
    /// Heights, um (NaN invalid).
    heights: Vec<f32>,
    /// Variance, um^2 (NaN unknown), when a camera came with one.
    variance: Option<Vec<f32>>,
    /// Source camera of each pixel.
    camera: Vec<u8>,
    /// Pixels left invalid because a camera lost the rows that would have covered them.
    pub lost_pixels: u64,
}

impl BandMap {
    /// The band's heights, um (NaN invalid).
    pub fn heights(&self) -> &[f32] {
        &self.heights[self.part.clone()]
    }

    /// The band's variance, um^2, when a camera came with one.
    pub fn variance(&self) -> Option<&[f32]> {
        self.variance.as_ref().map(|v| &v[self.part.clone()])
    }

    /// The band's source camera of each pixel.
    pub fn camera(&self) -> &[u8] {
        &self.camera[self.part.clone()]
    }
}

/// A band waiting for the turns: its layers (over `rows` and their halo), the turns they were
/// already moved by.
struct Pending {
    rows: Range<usize>,
    layers: Vec<Layer>,
    moved: Vec<i32>,
    /// Whether its edge pixels were gathered for the board's turn.
    sampled: bool,
}

/// Running sums of a seam (step 4), added band by band.
#[derive(Clone, Copy, Debug, Default)]
struct SeamSums {
    pixels: u64,
    flat: u64,
    step_sum: f64,
    along: ShiftSums,
    across: ShiftSums,
    off_turn_bands: u64,
}

/// The sums of the shift estimate along one axis: `b(p) = a(p + s) + k` over the pixels valid
/// in both layers, a gradient (Lucas-Kanade) estimate, `d = b - a = k + s g` solved by least
/// squares for `(k, s)`, with `g` the central difference along the shift of the two layers'
/// mean. No layer is interpolated: a search over interpolated shifts lowers the noise of the
/// interpolated samples away from whole pixels (`(1-f)^2 + f^2` of it) and so finds a false
/// minimum a fraction of a pixel off either way. No shift without texture (fewer than
/// [`MIN_WALL_PIXELS`] deposit-wall pixels) or beyond the first-order range (2 px).
#[derive(Clone, Copy, Debug, Default)]
struct ShiftSums {
    n: u64,
    walls: u64,
    sg: f64,
    sgg: f64,
    sd: f64,
    sdg: f64,
}

impl ShiftSums {
    /// The shift, px.
    fn shift(&self) -> Option<f64> {
        if self.walls < MIN_WALL_PIXELS as u64 || self.n < 100 {
            return None;
        }
        let nf = self.n as f64;
        let det = nf * self.sgg - self.sg * self.sg;
        if det.is_nan() || det <= 0.0 {
            return None;
        }
        let s = (nf * self.sdg - self.sg * self.sd) / det;
        (s.is_finite() && s.abs() <= 2.0).then_some(s)
    }
}

/// The blend from band to band: the turns once decided, the seams' sums, the bands waiting.
pub struct Blender {
    grid: BoardGrid,
    edge_px: usize,
    /// Turn of layer `k` against layer `k - 1` once decided (`[0]`: `Some(0)`).
    pair: Vec<Option<i32>>,
    /// The board's turn once decided.
    board: Option<i32>,
    /// Edge heights and heights per turn gathered for the board's turn.
    edge: (Vec<f32>, Vec<f32>),
    /// Per undecided pair: the differences and heights per turn gathered for its turn.
    shared: Vec<(Vec<f32>, Vec<f32>)>,
    edge_median_um: Option<f64>,
    edge_off_bands: u64,
    seams: Vec<SeamSums>,
    pending: VecDeque<Pending>,
    variance: bool,
}

impl Blender {
    /// A blend of `cameras` layers (in order across the board) on `grid`, the board's turn
    /// from the pixels within `edge_px` of its outline.
    pub fn new(grid: BoardGrid, cameras: usize, edge_px: usize) -> Blender {
        let mut pair = vec![None; cameras];
        if let Some(p) = pair.first_mut() {
            *p = Some(0);
        }
        Blender {
            grid,
            edge_px,
            pair,
            board: None,
            edge: (Vec::new(), Vec::new()),
            shared: vec![(Vec::new(), Vec::new()); cameras],
            edge_median_um: None,
            edge_off_bands: 0,
            seams: vec![SeamSums::default(); cameras.saturating_sub(1)],
            pending: VecDeque::new(),
            variance: false,
        }
    }

    /// The rows (with halo) a band of board rows `rows` needs its layers over.
    pub fn halo(&self, rows: &Range<usize>) -> Range<usize> {
        Blender::halo_of(&self.grid, rows)
    }

    /// [`Self::halo`] of a blend on `grid`.
    pub fn halo_of(grid: &BoardGrid, rows: &Range<usize>) -> Range<usize> {
        rows.start.saturating_sub(1)..(rows.end + 1).min(grid.rows)
    }

    /// The next band: board rows `rows` (following the last band's), with every camera's layer
    /// over [`Self::halo`] of them. Returns the bands the turns allow to be blended now, in
    /// order (none while a turn waits for evidence).
    pub fn band(&mut self, rows: Range<usize>, layers: Vec<Layer>) -> Vec<BandMap> {
        self.variance |= layers.iter().any(|l| l.variance.is_some());
        for k in 1..layers.len() {
            let (mut d, mut t) = shared_differences(&layers[k - 1], &layers[k]);
            match self.pair[k] {
                None => {
                    // Gathered over the bands until there are enough.
                    let e = &mut self.shared[k];
                    e.0.append(&mut d);
                    e.1.append(&mut t);
                    if e.0.len() >= MIN_SHARED {
                        let (d, t) = std::mem::take(e);
                        self.pair[k] = turns_to_zero(d, t);
                    }
                }
                Some(held) => {
                    if d.len() >= MIN_SHARED && turns_to_zero(d, t).is_some_and(|t| t != held) {
                        self.seams[k - 1].off_turn_bands += 1;
                    }
                }
            }
        }
        let n = layers.len();
        self.pending.push_back(Pending {
            rows,
            layers,
            moved: vec![0; n],
            sampled: false,
        });
        self.flush(false)
    }

    /// No more bands: undecided turns are 0; every waiting band is blended.
    pub fn end(&mut self) -> Vec<BandMap> {
        self.flush(true)
    }

    /// Whole turns of each layer (camera turns, then the board's; 0 where undecided).
    fn turns(&self) -> Vec<i32> {
        let mut acc = 0;
        self.pair
            .iter()
            .map(|p| {
                acc += p.unwrap_or(0);
                acc + self.board.unwrap_or(0)
            })
            .collect()
    }

    fn flush(&mut self, ended: bool) -> Vec<BandMap> {
        if ended {
            // A pair with fewer shared pixels than needed decides on what it has.
            for (p, e) in self.pair.iter_mut().zip(&mut self.shared) {
                if p.is_none() {
                    let (d, t) = std::mem::take(e);
                    *p = Some(turns_to_zero(d, t).unwrap_or(0));
                }
            }
        }
        if self.pair.iter().any(Option::is_none) {
            return Vec::new();
        }
        // The board's turn from the waiting bands' edge pixels, on the cameras' turns.
        if self.board.is_none() {
            let turns = self.turns();
            for p in self.pending.iter_mut().filter(|p| !p.sampled) {
                p.sampled = true;
                move_layers(p, &turns);
                let (h, t) = edge_pixels(&p.layers, &p.rows, &self.grid, self.edge_px, Edge::All);
                self.edge.0.extend(h);
                self.edge.1.extend(t);
            }
            if self.edge.0.len() >= MIN_EDGE || ended {
                let (h, t) = std::mem::take(&mut self.edge);
                self.edge_median_um = median(h.clone()).map(f64::from);
                self.board = Some(turns_to_zero(h, t).unwrap_or(0));
            } else {
                return Vec::new();
            }
        }
        let turns = self.turns();
        let mut out = Vec::with_capacity(self.pending.len());
        while let Some(mut p) = self.pending.pop_front() {
            move_layers(&mut p, &turns);
            // The band's side edges, and its rows of the leading or trailing edge, each on
            // their own: the trailing edge is checked whatever the sides say.
            for part in [Edge::Sides, Edge::Ends] {
                let (h, t) = edge_pixels(&p.layers, &p.rows, &self.grid, self.edge_px, part);
                if h.len() < MIN_EDGE / 5 {
                    continue;
                }
                if turns_to_zero(h, t).is_some_and(|k| k != 0) {
                    self.edge_off_bands += 1;
                }
            }
            out.push(self.blend_band(&p));
            p.layers.into_iter().for_each(Layer::recycle);
        }
        out
    }

    /// Steps 3 and 4 on a band whose layers sit on their turns.
    fn blend_band(&mut self, p: &Pending) -> BandMap {
        let grid = &self.grid;
        let halo = self.halo(&p.rows);
        let map = mix_rows(&p.layers, grid, halo.clone(), self.variance);
        for k in 1..p.layers.len() {
            add_seam(
                &mut self.seams[k - 1],
                (&p.layers[k - 1], &p.layers[k]),
                &map,
                p.rows.clone(),
                grid,
            );
        }
        // The band's rows out of the halo's.
        let w = grid.width;
        let (a, b) = (
            (p.rows.start - halo.start) * w,
            (p.rows.end - halo.start) * w,
        );
        // Only a camera that lost rows has lost pixels (a pass over the band's pixels
        // otherwise spared).
        let lost_pixels = if p.layers.iter().all(|l| l.lost.is_empty()) {
            0
        } else {
            p.rows
                .clone()
                .flat_map(|r| (0..w).map(move |c| (r, c)))
                .zip(&map.heights[a..b])
                .filter(|&((r, c), h)| !h.is_finite() && p.layers.iter().any(|l| l.is_lost(r, c)))
                .count() as u64
        };
        BandMap {
            rows: p.rows.clone(),
            part: a..b,
            heights: map.heights,
            variance: map.variance,
            camera: map.camera,
            lost_pixels,
        }
    }

    /// The turns, the edge's median, the seams: what the bands decided and added up. The
    /// buffers kept for later bands are dropped.
    pub fn finish(self) -> (Vec<i32>, Option<f64>, u64, Vec<Seam>) {
        crate::pool::clear();
        let to_um = self.grid.pitch_mm * 1000.0;
        let seams = self
            .seams
            .iter()
            .enumerate()
            .map(|(k, s)| Seam {
                cameras: (k, k + 1),
                pixels: s.pixels,
                flat_pixels: s.flat,
                height_step_um: (s.flat > 0).then(|| s.step_sum / s.flat as f64),
                shift_x_um: s.along.shift().map(|v| v * to_um),
                shift_y_um: s.across.shift().map(|v| v * to_um),
                off_turn_bands: s.off_turn_bands,
            })
            .collect();
        (
            self.turns(),
            self.edge_median_um,
            self.edge_off_bands,
            seams,
        )
    }
}

/// Moves a waiting band's layers onto `turns`.
fn move_layers(p: &mut Pending, turns: &[i32]) {
    for ((l, m), &t) in p.layers.iter_mut().zip(&mut p.moved).zip(turns) {
        shift(l, t - *m);
        *m = t;
    }
}

/// The whole turns that bring the median of `d` nearest zero, with `t` the heights per turn
/// there: a layer onto the previous one (step 1; `d` the later minus the earlier over their
/// shared valid pixels) or the map onto the board's edge (step 2; `d` the edge heights).
/// `None` without samples.
fn turns_to_zero(d: Vec<f32>, t: Vec<f32>) -> Option<i32> {
    let (d, t) = (median(d)?, median(t)?);
    (t > 0.0).then(|| (-d / t).round() as i32)
}

/// The differences (`cur` minus `prev`) over the two layers' shared valid pixels, and `cur`'s
/// heights per turn there.
fn shared_differences(prev: &Layer, cur: &Layer) -> (Vec<f32>, Vec<f32>) {
    let mut d = Vec::new();
    let mut t = Vec::new();
    // Over the shared window, in board order (outside it one of the two is NaN).
    let (rows, cols) = prev.overlap(cur);
    for r in rows {
        for c in cols.clone() {
            let (Some(ia), Some(ib)) = (prev.index(r, c), cur.index(r, c)) else {
                continue;
            };
            let (a, b) = (prev.heights.data[ia], cur.heights.data[ib]);
            if a.is_finite() && b.is_finite() {
                d.push(b - a);
                t.push(cur.period_um.data[ib]);
            }
        }
    }
    (d, t)
}

/// Which of a band's board-edge pixels.
#[derive(Clone, Copy, PartialEq)]
enum Edge {
    /// Every pixel within `edge_px` of the outline.
    All,
    /// Those of the side edges (the columns), outside the leading and trailing rows.
    Sides,
    /// Those of the leading and trailing edge rows.
    Ends,
}

/// The blended heights and heights per turn of the valid board-edge pixels of board rows
/// `rows` (within `edge_px` of the outline; `part` of them).
fn edge_pixels(
    layers: &[Layer],
    rows: &Range<usize>,
    grid: &BoardGrid,
    edge_px: usize,
    part: Edge,
) -> (Vec<f32>, Vec<f32>) {
    let (mut h, mut t) = (Vec::new(), Vec::new());
    let w = grid.width;
    for r in rows.clone() {
        let end = r < edge_px || r + edge_px >= grid.rows;
        let cols: [Range<usize>; 2] = match (part, end || 2 * edge_px >= w) {
            (Edge::Sides, true) | (Edge::Ends, false) => continue,
            (_, true) => [0..w, 0..0],
            (_, false) => [0..edge_px, w - edge_px..w],
        };
        for c in cols.into_iter().flatten() {
            if let Some((hm, tm)) = mix_at(layers, r, c) {
                h.push(hm);
                t.push(tm);
            }
        }
    }
    (h, t)
}

/// The blended height and height per turn at board pixel `(r, c)` (step 3's weighted means),
/// `None` where no layer is valid.
fn mix_at(layers: &[Layer], r: usize, c: usize) -> Option<(f32, f32)> {
    let (mut s, mut ts, mut ws) = (0.0f64, 0.0f64, 0.0f64);
    for l in layers {
        let Some(i) = l.index(r, c) else {
            continue;
        };
        let (h, w) = (l.heights.data[i], l.weight.data[i]);
        if h.is_finite() && w > 0.0 {
            let wf = f64::from(w);
            s += wf * f64::from(h);
            ts += wf * f64::from(l.period_um.data[i]);
            ws += wf;
        }
    }
    (ws > 0.0).then(|| ((s / ws) as f32, (ts / ws) as f32))
}

/// Hands a band's buffers on to later bands (its rows are in the map; [`crate::pool`]).
pub(crate) fn recycle(m: BandMap) {
    crate::pool::BAND_F32.give(m.heights);
    if let Some(v) = m.variance {
        crate::pool::BAND_F32.give(v);
    }
    crate::pool::BAND_U8.give(m.camera);
}

/// Blended rows of the map: board rows `rows`, row-major over the grid's width.
struct MapRows {
    rows: Range<usize>,
    heights: Vec<f32>,
    variance: Option<Vec<f32>>,
    camera: Vec<u8>,
}

impl MapRows {
    /// Height at board pixel `(r, c)` (`r` within the rows).
    fn at(&self, r: usize, c: usize, w: usize) -> f32 {
        self.heights[(r - self.rows.start) * w + c]
    }
}

/// Step 3 over board rows `rows`, in parallel over parts of them: every pixel is its own
/// weighted mean.
fn mix_rows(layers: &[Layer], grid: &BoardGrid, rows: Range<usize>, variance: bool) -> MapRows {
    let w = grid.width;
    let n = rows.len() * w;
    // Buffers of bands already in the map ([`recycle`]; fresh pages from the system, zeroed
    // by the kernel, cost more than the mix itself): every pixel is written by `mix_part`.
    let mut heights = crate::pool::BAND_F32.take(n, 0.0);
    let mut vars = variance.then(|| crate::pool::BAND_F32.take(n, 0.0));
    let mut camera = crate::pool::BAND_U8.take(n, 0);
    let threads = std::thread::available_parallelism().map_or(1, |t| t.get());
    let part_rows = rows.len().div_ceil(threads.max(1)).max(1);
    let part = part_rows * w;
    std::thread::scope(|sc| {
        let parts = heights
            .chunks_mut(part.max(1))
            .zip(
                vars.as_deref_mut()
                    .unwrap_or(&mut [][..])
                    .chunks_mut(part.max(1))
                    .map(Some)
                    .chain(std::iter::repeat_with(|| None)),
            )
            .zip(camera.chunks_mut(part.max(1)))
            .enumerate();
        for (k, ((hs, vs), cs)) in parts {
            let r0 = rows.start + k * part_rows;
            sc.spawn(move || mix_part(layers, r0, w, (hs, vs, cs)));
        }
    });
    MapRows {
        rows,
        heights,
        variance: vars,
        camera,
    }
}

/// One pixel's sums over the layers in step 3.
#[derive(Clone, Copy)]
struct Mix {
    /// Weighted heights, weights, squared weights times variances.
    s: f64,
    ws: f64,
    vs: f64,
    /// The largest weight so far and its layer.
    best: (f32, u8),
}

impl Mix {
    const NONE: Mix = Mix {
        s: 0.0,
        ws: 0.0,
        vs: 0.0,
        best: (0.0, NO_CAMERA),
    };
}

/// Step 3 over whole board rows from `r0` (`w` pixels each) into `hs` (heights), `vs`
/// (variances, when kept) and `cs` (cameras), every pixel written. Row by row, each layer adds
/// its window's part of the row in turn: every pixel's sums take the layers in their order,
/// as a pixel at a time would.
fn mix_part(
    layers: &[Layer],
    r0: usize,
    w: usize,
    (hs, mut vs, cs): (&mut [f32], Option<&mut [f32]>, &mut [u8]),
) {
    let mut acc = vec![Mix::NONE; w];
    let mut cuts: Vec<usize> = Vec::with_capacity(2 * layers.len() + 2);
    for (k_row, (h_out, c_out)) in hs
        .chunks_mut(w.max(1))
        .zip(cs.chunks_mut(w.max(1)))
        .enumerate()
    {
        let r = r0 + k_row;
        if vs.is_none() {
            mix_row_by_cover(layers, r, h_out, c_out, &mut cuts, &mut acc);
            continue;
        }
        acc.fill(Mix::NONE);
        for (k, l) in layers.iter().enumerate() {
            add_layer_row(&mut acc, l, r, k.min(254) as u8);
        }
        let v_out = vs
            .as_deref_mut()
            .map(|v| &mut v[k_row * w..(k_row + 1) * w]);
        for (j, m) in acc.iter().enumerate() {
            let valid = m.ws > 0.0;
            h_out[j] = if valid { (m.s / m.ws) as f32 } else { f32::NAN };
            c_out[j] = if valid { m.best.1 } else { NO_CAMERA };
        }
        if let Some(v_out) = v_out {
            for (o, m) in v_out.iter_mut().zip(&acc) {
                *o = if m.ws > 0.0 {
                    (m.vs / (m.ws * m.ws)) as f32
                } else {
                    f32::NAN
                };
            }
        }
    }
}

/// [`mix_part`]'s row `r` without variances, the same values: in the columns that one
/// layer's window alone covers (all but the seams), each pixel is that layer's height where
/// it is valid (`(w h) / w` is `h`: the product of two `f32` is exact in `f64`, and so is
/// the quotient; `+ 0.0` gives the sums' `+0` for a `-0`), and its camera; where windows
/// overlap, the sums of [`add_layer_row`]; where none reaches, invalid.
fn mix_row_by_cover(
    layers: &[Layer],
    r: usize,
    h_out: &mut [f32],
    c_out: &mut [u8],
    cuts: &mut Vec<usize>,
    acc: &mut Vec<Mix>,
) {
    let w = h_out.len();
    let cols = |l: &Layer| l.cols.start.min(w)..l.cols.end.min(w);
    let live = |l: &&Layer| l.rows.contains(&r) && !cols(l).is_empty();
    cuts.clear();
    cuts.extend([0, w]);
    for l in layers.iter().filter(live) {
        cuts.extend([cols(l).start, cols(l).end]);
    }
    cuts.sort_unstable();
    cuts.dedup();
    for seg in cuts.windows(2) {
        let (a, b) = (seg[0], seg[1]);
        let mut over = layers
            .iter()
            .enumerate()
            .filter(|(_, l)| live(l) && cols(l).start <= a && b <= cols(l).end);
        let (h_seg, c_seg) = (&mut h_out[a..b], &mut c_out[a..b]);
        match (over.next(), over.next()) {
            (None, _) => {
                h_seg.fill(f32::NAN);
                c_seg.fill(NO_CAMERA);
            }
            (Some((k, l)), None) => {
                let at = (r - l.rows.start) * l.cols.len() + (a - l.cols.start);
                let (hs, ws) = (
                    &l.heights.data[at..at + (b - a)],
                    &l.weight.data[at..at + (b - a)],
                );
                let k = k.min(254) as u8;
                for (((o, c), &h), &wt) in h_seg.iter_mut().zip(c_seg.iter_mut()).zip(hs).zip(ws) {
                    let valid = h.is_finite() && wt > 0.0;
                    *o = if valid { h + 0.0 } else { f32::NAN };
                    *c = if valid { k } else { NO_CAMERA };
                }
            }
            _ => {
                acc.clear();
                acc.resize(b - a, Mix::NONE);
                for (k, l) in layers.iter().enumerate() {
                    if live(&l) && cols(l).start <= a && b <= cols(l).end {
                        let at = (r - l.rows.start) * l.cols.len() + (a - l.cols.start);
                        add_part(acc, l, at, k.min(254) as u8);
                    }
                }
                for ((o, c), m) in h_seg.iter_mut().zip(c_seg.iter_mut()).zip(acc.iter()) {
                    let valid = m.ws > 0.0;
                    *o = if valid { (m.s / m.ws) as f32 } else { f32::NAN };
                    *c = if valid { m.best.1 } else { NO_CAMERA };
                }
            }
        }
    }
}

/// Adds layer `l` (number `k`) at board row `r` to the sums of the row's pixels `acc`.
fn add_layer_row(acc: &mut [Mix], l: &Layer, r: usize, k: u8) {
    if !l.rows.contains(&r) {
        return;
    }
    let cols = l.cols.start.min(acc.len())..l.cols.end.min(acc.len());
    let at = (r - l.rows.start) * l.cols.len();
    add_part(&mut acc[cols], l, at, k);
}

/// Adds layer `l`'s pixels from its window index `at` on, one to each of `acc`.
fn add_part(acc: &mut [Mix], l: &Layer, at: usize, k: u8) {
    let n = acc.len();
    let (hs, ws) = (&l.heights.data[at..at + n], &l.weight.data[at..at + n]);
    // A camera without a variance leaves the pixel's unknown (NaN).
    let vs = l.variance.as_ref().map(|v| &v.data[at..at + n]);
    for (j, m) in acc.iter_mut().enumerate() {
        let (h, w) = (hs[j], ws[j]);
        if h.is_finite() && w > 0.0 {
            let wf = f64::from(w);
            m.s += wf * f64::from(h);
            m.ws += wf;
            m.vs += wf * wf * vs.map_or(f64::NAN, |v| f64::from(v[j]));
            if w > m.best.0 {
                m.best = (w, k);
            }
        }
    }
}

/// Blends whole `layers` (in order across the board) on `grid` in one band; see the module
/// docs.
pub fn blend(layers: &mut [Layer], grid: &BoardGrid, edge_px: usize) -> Blended {
    let mut b = Blender::new(*grid, layers.len(), edge_px);
    let taken: Vec<Layer> = layers
        .iter_mut()
        .map(|l| std::mem::replace(l, Layer::empty(0..0, 0..0, false)))
        .collect();
    let mut bands = b.band(0..grid.rows, taken);
    bands.extend(b.end());
    let mut heights = Grid::invalid(grid.width, grid.rows);
    let mut variance = bands
        .iter()
        .any(|m| m.variance.is_some())
        .then(|| Grid::invalid(grid.width, grid.rows));
    let mut camera = vec![NO_CAMERA; grid.rows * grid.width];
    for m in bands {
        let a = m.rows.start * grid.width;
        let n = m.part.len();
        heights.data[a..a + n].copy_from_slice(m.heights());
        camera[a..a + n].copy_from_slice(m.camera());
        if let (Some(v), Some(mv)) = (variance.as_mut(), m.variance()) {
            v.data[a..a + n].copy_from_slice(mv);
        }
    }
    let (turns, edge_median_um, edge_off_bands, seams) = b.finish();
    Blended {
        heights,
        variance,
        camera,
        turns,
        edge_median_um,
        edge_off_bands,
        seams,
    }
}

fn shift(l: &mut Layer, turns: i32) {
    if turns == 0 {
        return;
    }
    for (h, t) in l.heights.data.iter_mut().zip(&l.period_um.data) {
        *h += turns as f32 * t;
    }
}

/// True when pixel `(r, c)` of the map is flat board: its 3 x 3 neighbourhood valid with a
/// range below [`FLAT_RANGE_UM`] (the board's outermost rows and columns never are; `map`
/// holds rows `r - 1..=r + 1`).
fn is_flat(map: &MapRows, grid: &BoardGrid, r: usize, c: usize) -> bool {
    let w = grid.width;
    if r == 0 || c == 0 || r + 1 >= grid.rows || c + 1 >= w {
        return false;
    }
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    for rr in r - 1..=r + 1 {
        for cc in c - 1..=c + 1 {
            let h = map.at(rr, cc, w);
            lo = lo.min(h);
            hi = hi.max(h);
        }
    }
    lo.is_finite() && hi.is_finite() && hi - lo < FLAT_RANGE_UM
}

/// Adds board rows `rows` of the seam between layers `a` and `b` (their halo rows give the
/// neighbours) to `s`.
fn add_seam(
    s: &mut SeamSums,
    (a, b): (&Layer, &Layer),
    map: &MapRows,
    rows: Range<usize>,
    grid: &BoardGrid,
) {
    let (shared_rows, cols) = a.overlap(b);
    let rows = rows.start.max(shared_rows.start)..rows.end.min(shared_rows.end);
    // Board pixel `(r, c)` of a layer; NaN outside the board and the layer's window.
    let at = |l: &Layer, r: i64, c: i64| -> f64 {
        if r < 0 || c < 0 {
            f64::NAN
        } else {
            f64::from(l.height(r as usize, c as usize))
        }
    };
    for r in rows {
        for c in cols.clone() {
            let (ha, hb) = (a.height(r, c), b.height(r, c));
            if !(ha.is_finite() && hb.is_finite()) {
                continue;
            }
            s.pixels += 1;
            if is_flat(map, grid, r, c) {
                s.flat += 1;
                s.step_sum += f64::from(hb - ha);
            }
            let (ri, ci) = (r as i64, c as i64);
            for ((dr, dc), sums) in [((1i64, 0i64), &mut s.along), ((0, 1), &mut s.across)] {
                let (a0, b0) = (f64::from(ha), f64::from(hb));
                let (ap, bp) = (at(a, ri + dr, ci + dc), at(b, ri + dr, ci + dc));
                let (am, bm) = (at(a, ri - dr, ci - dc), at(b, ri - dr, ci - dc));
                if ![ap, bp, am, bm].iter().all(|v| v.is_finite()) {
                    continue;
                }
                if (bp - b0).abs() > f64::from(WALL_UM) {
                    sums.walls += 1;
                }
                let g = 0.25 * ((ap + bp) - (am + bm));
                let d = b0 - a0;
                sums.n += 1;
                sums.sg += g;
                sums.sgg += g * g;
                sums.sd += d;
                sums.sdg += d * g;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::resample::{resample, CameraPlacement, Source};

    /// Truth on the board: a bow (0 at the edges) and paste boxes whose walls slope over
    /// 0.1 mm (as a camera's pixel integration and blur make them; a point-sampled step
    /// would hide where its edge lies within a pixel).
    fn truth(x: f64, y: f64, len: f64, wid: f64) -> f64 {
        let (xi, eta) = (2.0 * x / len - 1.0, 2.0 * y / wid - 1.0);
        let bow = 900.0 * (1.0 - xi * xi) * (1.0 - eta * eta);
        // Distance inside the box [0.1, 0.5) x [0.1, 0.6) of each 1 mm cell, mm.
        let (u, v) = (x.rem_euclid(1.0), y.rem_euclid(1.0));
        let inside = (u - 0.1).min(0.5 - u).min(v - 0.1).min(0.6 - v);
        bow + 120.0 * (inside / 0.1 + 0.5).clamp(0.0, 1.0)
    }

    /// A camera of `cols x rows` pixels on a 0.03 mm grid at `y0` across, placed (by its
    /// calibration) `dy` mm off where its pixels really sit, seeing `height` (um at board
    /// `(x, y)`), resampled onto `grid` with a height per turn of `t`.
    fn layer(
        y0: f64,
        dy: f64,
        (cols, rows): (usize, usize),
        t: f32,
        height: impl Fn(f64, f64) -> f64,
        grid: &BoardGrid,
    ) -> Layer {
        let place = CameraPlacement {
            x0_mm: 0.0,
            y0_mm: y0,
            row_mm: 0.03,
            pitch_mm: 0.03,
            rotation_rad: 0.0,
        };
        let real = CameraPlacement {
            y0_mm: y0 - dy,
            ..place
        };
        let mut cam = Grid::invalid(cols, rows);
        for b in 0..rows {
            for c in 0..cols {
                let (x, y) = real.to_board(b as f64, c as f64);
                *cam.at_mut(b, c) = height(x, y) as f32;
            }
        }
        let src = Source {
            heights: &cam,
            variance: None,
            period_um: &vec![t; cols],
            row0: 0,
            first_row: 0,
            places: None,
            lost_rows: &[],
        };
        resample(&src, &place, grid, 0..grid.rows, 15.0)
    }

    /// Without variances, a row is mixed by the layers' cover (one layer's pixels taken as
    /// they are): the same heights and cameras, bit for bit, as the sums over every layer
    /// that the variances' path still makes; windows that overlap, end mid-band, reach past
    /// the grid and miss rows; invalid pixels, zero weights and `-0` heights.
    #[test]
    fn a_row_by_cover_is_the_weighted_sums() {
        let mut rng = crate::test_rng::Lcg(5);
        let mut rnd = || rng.next();
        let (w, rows) = (300usize, 40usize);
        let windows = [
            (0..30, 0..120),
            (5..40, 100..210),
            (0..40, 190..330),
            (12..20, 50..60),
        ];
        let layers: Vec<Layer> = windows
            .iter()
            .map(|(rs, cs)| {
                let mut l = Layer::empty(rs.clone(), cs.clone(), false);
                for (h, wt) in l.heights.data.iter_mut().zip(l.weight.data.iter_mut()) {
                    let u = rnd();
                    *h = match (u * 20.0) as u32 {
                        0 => f32::NAN,
                        1 => -0.0,
                        _ => (300.0 * rnd() - 100.0) as f32,
                    };
                    *wt = if u > 0.97 {
                        0.0
                    } else {
                        rnd().max(1e-3) as f32
                    };
                }
                l
            })
            .collect();
        let n = rows * w;
        let (mut h1, mut c1) = (vec![0.0f32; n], vec![0u8; n]);
        let (mut h2, mut v2, mut c2) = (vec![0.0f32; n], vec![0.0f32; n], vec![0u8; n]);
        mix_part(&layers, 0, w, (&mut h1, None, &mut c1));
        mix_part(&layers, 0, w, (&mut h2, Some(&mut v2), &mut c2));
        assert_eq!(c1, c2);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert!(bits(&h1) == bits(&h2));
        let valid = c1.iter().filter(|&&c| c != NO_CAMERA).count();
        assert!(valid > n / 2 && h1.iter().any(|h| h.is_nan()));
    }

    #[test]
    fn three_cameras_turn_aligned_anchored_and_seams_measured() {
        let (len, wid) = (12.0, 9.0);
        let grid = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.03,
            rows: 400,
            width: 300,
        };
        let t = 400.0f32;
        // Three cameras of 120 columns, 0.5 mm overlaps; the middle one misplaced by 6 um
        // across (its placement says y0 + 0.006 mm, the pixels sit at y0); each unwrapped
        // to another turn: 0, +1, -2.
        let mut layers: Vec<Layer> = [0.0, 3.1, 6.2]
            .into_iter()
            .enumerate()
            .map(|(k, y0)| {
                let off = f64::from([0.0, 1.0, -2.0][k] * t);
                let dy = if k == 1 { 0.006 } else { 0.0 };
                layer(
                    y0,
                    dy,
                    (120, 400),
                    t,
                    |x, y| truth(x, y, len, wid) + off,
                    &grid,
                )
            })
            .collect();
        let out = blend(&mut layers, &grid, 3);
        assert_eq!(out.turns, vec![0, -1, 2]);
        // Absolute heights against the truth (bilinear on paste walls aside).
        let mut errs = Vec::new();
        for i in 0..grid.rows {
            for j in 0..grid.width {
                let (x, y) = grid.centre(i, j);
                let h = out.heights.at(i, j);
                if h.is_finite() {
                    errs.push((f64::from(h) - truth(x, y, len, wid)).abs());
                }
            }
        }
        errs.sort_by(f64::total_cmp);
        assert!(
            errs[errs.len() / 2] < 1.0,
            "median error {}",
            errs[errs.len() / 2]
        );
        assert!(errs.len() > grid.rows * grid.width * 9 / 10);
        // Seams: flat steps near 0; the 6 um misplacement of camera 1 seen across.
        for s in &out.seams {
            assert!(s.height_step_um.unwrap().abs() < 1.0, "{s:?}");
        }
        let y01 = out.seams[0].shift_y_um.unwrap();
        let y12 = out.seams[1].shift_y_um.unwrap();
        assert!((y01.abs() - 6.0).abs() < 2.0, "{y01}");
        assert!((y12.abs() - 6.0).abs() < 2.0, "{y12}");
        assert!(y01 * y12 < 0.0);
        assert!(out.seams[0].shift_x_um.unwrap().abs() < 2.0);
        assert!(out.camera.contains(&2));
    }

    #[test]
    fn the_boards_turn_moves_every_camera_and_the_map() {
        // Every camera a whole turn off, the edges included: step 2 must bring the map back.
        let (len, wid) = (6.0, 6.0);
        let grid = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.03,
            rows: 200,
            width: 200,
        };
        let t = 400.0f32;
        let mut layers: Vec<Layer> = [(0.0, 1.0), (3.0, 2.0)]
            .into_iter()
            .map(|(y0, turns)| {
                let off = f64::from(turns * t);
                layer(
                    y0,
                    0.0,
                    (110, 200),
                    t,
                    |x, y| truth(x, y, len, wid) * 0.1 + off,
                    &grid,
                )
            })
            .collect();
        let out = blend(&mut layers, &grid, 3);
        assert_eq!(out.turns, vec![-1, -2]);
        assert!(out.variance.is_none());
        let mut n = 0;
        for i in 0..grid.rows {
            for j in 0..grid.width {
                let h = out.heights.at(i, j);
                if h.is_finite() {
                    let (x, y) = grid.centre(i, j);
                    assert!(
                        (f64::from(h) - truth(x, y, len, wid) * 0.1).abs() < 15.0,
                        "({i}, {j}) {h}"
                    );
                    n += 1;
                }
            }
        }
        assert!(n > grid.rows * grid.width * 9 / 10, "{n}");
    }
}
