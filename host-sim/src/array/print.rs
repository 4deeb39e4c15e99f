//! The print: solder paste printed through a stencil onto the pads of a paste layer, with
//! known defects, as height fields in board millimetres (`docs/inspection.md`, "Printing paste
//! (simulator)").
//!
//! A [`Deposit`] is one body of material on the board: an [`Outline`] in the *board* frame, a
//! plateau height, a smooth wall (`h * smoothstep(-sd / edge)` with the outline's signed
//! distance `sd`, so the footprint is exactly the outline) and Gaussian dog-ears. Its
//! [`Deposit::height`] is the truth the renderer draws and the inspection integrates; its
//! [`Deposit::volume`] is exact (closed form over the wall for discs and rounded rectangles).
//! Heights of overlapping deposits add. [`DepositIndex`] bins deposits on a grid so that
//! [`paste_height`] costs a few outline evaluations per point, whatever the board.
//!
//! [`print`](fn@print) fills every opening of the layer to `stencil x TE(AR)` of its volume
//! ([`transfer_efficiency`] of the area ratio), slumps it, offsets it (one print offset per
//! board, scatter per pad), puts dog-ears on some rectangular openings, injects the requested
//! defects at random pads and records the truth per pad ([`PrintedPad`]). Fiducials are copper
//! discs ([`Material::Copper`]). Everything is drawn from the seed: the same inputs give the
//! same [`Print`].

use crate::inspection::pads::{Outline, Pad, Point, Rigid};
use rand::seq::SliceRandom;
use rand::RngExt;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// What a deposit is made of (how it reflects: paste has its own background and contrast).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Material {
    /// Solder paste.
    Paste,
    /// Copper (a fiducial): reflects like the board.
    Copper,
}

/// A Gaussian bump on a deposit (a dog-ear), added where the deposit is.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bump {
    /// Centre, board frame, mm.
    pub centre: Point,
    /// Gaussian radius, mm.
    pub sigma_mm: f64,
    /// Peak height, um.
    pub height_um: f64,
}

impl Bump {
    /// Height of the bump alone at `p`, um.
    pub fn at(&self, p: Point) -> f64 {
        let (dx, dy) = (p[0] - self.centre[0], p[1] - self.centre[1]);
        self.height_um * (-(dx * dx + dy * dy) / (2.0 * self.sigma_mm * self.sigma_mm)).exp()
    }
}

/// One body of material on the board.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Deposit {
    /// Footprint, board frame, mm.
    pub outline: Outline,
    /// Plateau height, um.
    pub height_um: f64,
    /// Width of the smooth wall inside the footprint, mm (0: a sharp wall).
    pub edge_mm: f64,
    /// Dog-ears.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub bumps: Vec<Bump>,
    /// What it is made of: paste, or copper for a fiducial.
    pub material: Material,
    /// The pad (index in the layer) this deposit belongs to; `None` for a bridge strip, a
    /// fiducial or a random-box deposit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pad: Option<usize>,
}

/// `3 t^2 - 2 t^3` (`t` in 0..=1).
pub fn smoothstep(t: f64) -> f64 {
    t * t * (3.0 - 2.0 * t)
}

/// Three-point Gauss-Legendre nodes and weights on -1..1 (exact for degree 5).
const GAUSS3: [(f64, f64); 3] = [
    (-0.774_596_669_241_483_4, 5.0 / 9.0),
    (0.0, 8.0 / 9.0),
    (0.774_596_669_241_483_4, 5.0 / 9.0),
];

/// `\int w dA` over an outline with the wall profile `w = smoothstep(min(-sd / edge, 1))`, mm^2:
/// the area a plateau height multiplies. Exact for discs and rounded rectangles (the co-area
/// formula over the inner offset curves, whose length is known: `P - 2 pi t` while the depth
/// `t` is within the corner radius, `2 (a + b) - 8 t` beyond), sampled on a 400 x 400 grid for
/// polygons.
pub fn effective_area(outline: &Outline, edge_mm: f64) -> f64 {
    if edge_mm <= 0.0 {
        return outline.area();
    }
    let g = |t: f64| smoothstep((t / edge_mm).min(1.0));
    // Length of the level set at depth t, breakpoint (corner radius) and the largest depth.
    let (len, knee, depth): (Box<dyn Fn(f64) -> f64>, f64, f64) = match outline {
        Outline::Circle { diameter, .. } => {
            let r = diameter / 2.0;
            (Box::new(move |t| 2.0 * PI * (r - t)), r, r)
        }
        Outline::RoundRect { size, radius, .. } => {
            let (a, b) = (size[0], size[1]);
            let r = radius.clamp(0.0, a.min(b) / 2.0);
            let p0 = 2.0 * (a + b) - (8.0 - 2.0 * PI) * r;
            (
                Box::new(move |t| {
                    if t <= r {
                        p0 - 2.0 * PI * t
                    } else {
                        2.0 * (a + b) - 8.0 * t
                    }
                }),
                r,
                a.min(b) / 2.0,
            )
        }
        Outline::Polygon { .. } => {
            let b = outline.bbox();
            let n = 400usize;
            let (sx, sy) = ((b[2] - b[0]) / n as f64, (b[3] - b[1]) / n as f64);
            let mut sum = 0.0;
            for j in 0..n {
                for i in 0..n {
                    let p = [b[0] + (i as f64 + 0.5) * sx, b[1] + (j as f64 + 0.5) * sy];
                    let sd = outline.signed_distance(p);
                    if sd < 0.0 {
                        sum += g(-sd);
                    }
                }
            }
            return sum * sx * sy;
        }
    };
    let mut cuts = vec![0.0, depth];
    for c in [knee, edge_mm] {
        if c > 0.0 && c < depth {
            cuts.push(c);
        }
    }
    cuts.sort_by(f64::total_cmp);
    let mut sum = 0.0;
    for w in cuts.windows(2) {
        let (lo, hi) = (w[0], w[1]);
        let (mid, half) = ((lo + hi) / 2.0, (hi - lo) / 2.0);
        for (x, wt) in GAUSS3 {
            let t = mid + half * x;
            sum += wt * half * g(t) * len(t);
        }
    }
    sum
}

impl Deposit {
    /// Height of this deposit at board point `p`, um (0 outside its outline).
    pub fn height(&self, p: Point) -> f64 {
        let sd = self.outline.signed_distance(p);
        if sd >= 0.0 {
            return 0.0;
        }
        let w = if self.edge_mm > 0.0 {
            smoothstep((-sd / self.edge_mm).min(1.0))
        } else {
            1.0
        };
        if self.bumps.is_empty() {
            return self.height_um * w;
        }
        let mut h = self.height_um;
        for b in &self.bumps {
            h += b.at(p);
        }
        h * w
    }

    /// Bounding box `[xmin, ymin, xmax, ymax]` (board mm) outside which the height is 0.
    pub fn reach_bbox(&self) -> [f64; 4] {
        self.outline.bbox()
    }

    /// Volume, um mm^2 (1 um mm^2 = 1e-3 mm^3): the plateau over the wall profile (exact,
    /// [`effective_area`]) plus the dog-ears (a 48 x 48 midpoint rule over +/-5 sigma).
    pub fn volume(&self) -> f64 {
        let mut v = self.height_um * effective_area(&self.outline, self.edge_mm);
        for b in &self.bumps {
            let n = 48;
            let h = 10.0 * b.sigma_mm / n as f64;
            let mut s = 0.0;
            for j in 0..n {
                for i in 0..n {
                    let p = [
                        b.centre[0] - 5.0 * b.sigma_mm + (i as f64 + 0.5) * h,
                        b.centre[1] - 5.0 * b.sigma_mm + (j as f64 + 0.5) * h,
                    ];
                    let sd = self.outline.signed_distance(p);
                    if sd < 0.0 {
                        let w = if self.edge_mm > 0.0 {
                            smoothstep((-sd / self.edge_mm).min(1.0))
                        } else {
                            1.0
                        };
                        s += w * b.at(p);
                    }
                }
            }
            v += s * h * h;
        }
        v
    }
}

/// Deposits binned on a grid of square cells: each cell lists (in increasing order) the
/// deposits whose reach box touches it, so a point's candidates are one slice.
#[derive(Clone, Debug, Default)]
pub struct DepositIndex {
    x0: f64,
    y0: f64,
    cell: f64,
    nx: usize,
    ny: usize,
    /// `ids[start[c]..start[c + 1]]` are cell `c`'s deposits.
    start: Vec<u32>,
    ids: Vec<u32>,
}

impl DepositIndex {
    /// Bins `deposits` in cells of 0.5 mm (larger when the deposits spread over more than
    /// 4 million such cells).
    pub fn new(deposits: &[Deposit]) -> DepositIndex {
        if deposits.is_empty() {
            return DepositIndex::default();
        }
        let mut b = [
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ];
        for d in deposits {
            let r = d.reach_bbox();
            b = [
                b[0].min(r[0]),
                b[1].min(r[1]),
                b[2].max(r[2]),
                b[3].max(r[3]),
            ];
        }
        let area = (b[2] - b[0]).max(1e-3) * (b[3] - b[1]).max(1e-3);
        let cell = 0.5f64.max((area / 4e6).sqrt());
        let nx = ((b[2] - b[0]) / cell).floor() as usize + 1;
        let ny = ((b[3] - b[1]) / cell).floor() as usize + 1;
        let mut idx = DepositIndex {
            x0: b[0],
            y0: b[1],
            cell,
            nx,
            ny,
            start: vec![0; nx * ny + 1],
            ids: Vec::new(),
        };
        let mut count = vec![0u32; nx * ny];
        for d in deposits {
            let (i0, i1, j0, j1) = idx.cells(&d.reach_bbox());
            for j in j0..=j1 {
                for c in &mut count[j * nx + i0..=j * nx + i1] {
                    *c += 1;
                }
            }
        }
        for (c, n) in count.iter().enumerate() {
            idx.start[c + 1] = idx.start[c] + n;
        }
        let mut fill: Vec<u32> = idx.start[..nx * ny].to_vec();
        idx.ids = vec![0; idx.start[nx * ny] as usize];
        for (k, d) in deposits.iter().enumerate() {
            let (i0, i1, j0, j1) = idx.cells(&d.reach_bbox());
            for j in j0..=j1 {
                for i in i0..=i1 {
                    let c = j * nx + i;
                    idx.ids[fill[c] as usize] = k as u32;
                    fill[c] += 1;
                }
            }
        }
        idx
    }

    /// Cell ranges `(i0, i1, j0, j1)` (inclusive, clamped) covering the box `r`.
    fn cells(&self, r: &[f64; 4]) -> (usize, usize, usize, usize) {
        let ix = |v: f64| (((v - self.x0) / self.cell).floor().max(0.0) as usize).min(self.nx - 1);
        let iy = |v: f64| (((v - self.y0) / self.cell).floor().max(0.0) as usize).min(self.ny - 1);
        (ix(r[0]), ix(r[2]), iy(r[1]), iy(r[3]))
    }

    /// Deposits that may be nonzero at `p` (increasing indices).
    pub fn at(&self, p: Point) -> &[u32] {
        if self.nx == 0 {
            return &[];
        }
        let (x, y) = ((p[0] - self.x0) / self.cell, (p[1] - self.y0) / self.cell);
        if !(x >= 0.0 && y >= 0.0) {
            return &[];
        }
        let (i, j) = (x as usize, y as usize);
        if i >= self.nx || j >= self.ny {
            return &[];
        }
        let c = j * self.nx + i;
        &self.ids[self.start[c] as usize..self.start[c + 1] as usize]
    }

    /// Deposits whose cells touch the box `r` (`[xmin, ymin, xmax, ymax]`), sorted, no
    /// repeats, into `out` (cleared first).
    pub fn in_box(&self, r: [f64; 4], out: &mut Vec<usize>) {
        out.clear();
        if self.nx == 0
            || r[2] < self.x0
            || r[3] < self.y0
            || r[0] > self.x0 + self.nx as f64 * self.cell
            || r[1] > self.y0 + self.ny as f64 * self.cell
        {
            return;
        }
        let (i0, i1, j0, j1) = self.cells(&r);
        for j in j0..=j1 {
            let a = self.start[j * self.nx + i0] as usize;
            let b = self.start[j * self.nx + i1 + 1] as usize;
            out.extend(self.ids[a..b].iter().map(|&k| k as usize));
        }
        out.sort_unstable();
        out.dedup();
    }
}

/// Sum of the deposits' heights at board point `p` (um) and whether paste is there (a paste
/// deposit with a positive height).
pub fn paste_height(deposits: &[Deposit], index: &DepositIndex, p: Point) -> (f64, bool) {
    let mut sum = 0.0;
    let mut paste = false;
    for &k in index.at(p) {
        let d = &deposits[k as usize];
        let h = d.height(p);
        if h > 0.0 {
            sum += h;
            paste |= d.material == Material::Paste;
        }
    }
    (sum, paste)
}

/// How many defects of each class to inject.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DefectCounts {
    /// No paste at all.
    pub missing: u32,
    /// 15-50 % of the opening volume (lower, and/or covering part of the opening).
    pub insufficient: u32,
    /// 150-200 % of the opening volume (taller and spread).
    pub excess: u32,
    /// Full volume shifted by 1/3 to 1/2 of the pad along one axis.
    pub offset: u32,
    /// Pairs of nearest neighbours (gap <= 0.5 mm) joined by a paste strip (both pads carry it).
    pub bridge: u32,
    /// A thin low (15-30 um) smear 0.2-0.5 of the pad beyond one side.
    pub smear: u32,
}

impl DefectCounts {
    /// Pads the counts take (a bridge takes two).
    pub fn pads(&self) -> u64 {
        u64::from(self.missing)
            + u64::from(self.insufficient)
            + u64::from(self.excess)
            + u64::from(self.offset)
            + 2 * u64::from(self.bridge)
            + u64::from(self.smear)
    }
}

/// The print process (scene table `[print]`); defaults are a good 100 um stencil print.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PrintParams {
    /// Stencil thickness, um (50..=250).
    pub stencil_um: f64,
    /// Slump: the footprint grows by this much all round, volume kept, mm (0..=0.1).
    pub slump_mm: f64,
    /// Width of a deposit's smooth wall, mm (0..=0.2).
    pub edge_mm: f64,
    /// Fraction of rectangular openings with dog-ears (0..=1).
    pub dog_ear_fraction: f64,
    /// Largest dog-ear height, um (each is 50-100 % of it; 0..=30).
    pub dog_ear_height_um: f64,
    /// Gaussian radius of a dog-ear, mm (0.005..=0.2).
    pub dog_ear_sigma_mm: f64,
    /// Print offset (stencil against the pads), one per board, sigma per axis, mm (0..=0.1;
    /// truncated at 3 sigma).
    pub offset_sigma_mm: f64,
    /// The print offset of this board (stencil against the pads, design frame, mm, each axis
    /// -0.5..=0.5): a printer's placement error as a print process sets it; absent, drawn
    /// from `offset_sigma_mm`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub offset_mm: Option<Point>,
    /// The print's rotation about the paste pattern's centre (the mean of the openings'
    /// centres), counter-clockwise, mrad (-10..=10): each deposit is moved by the turn at its
    /// opening's centre (not turned itself: a mrad over a pad's size is under a um).
    #[serde(skip_serializing_if = "is_zero")]
    pub rotation_mrad: f64,
    /// Every deposit's volume changed by this, percent (-50..=50): the paste's viscosity, the
    /// squeegee's pressure.
    #[serde(skip_serializing_if = "is_zero")]
    pub volume_pct: f64,
    /// Clogged apertures: the openings whose area ratio is below `clogging_area_ratio` print
    /// this much less paste, percent (0..=80).
    #[serde(skip_serializing_if = "is_zero")]
    pub clogging_pct: f64,
    /// See `clogging_pct` (0.3..=2; default 0.8: the fine-pitch apertures, which clog first).
    #[serde(skip_serializing_if = "is_default_clogging_area_ratio")]
    pub clogging_area_ratio: f64,
    /// Per-pad volume scatter, rms, percent (0..=20; truncated at 3 sigma).
    pub height_scatter_pct: f64,
    /// Per-pad position scatter, sigma per axis, mm (0..=0.05; truncated at 3 sigma).
    pub position_sigma_mm: f64,
    /// Height of a copper fiducial, um (1..=200).
    pub fiducial_height_um: f64,
    /// Wall width of a copper fiducial (an etched edge), mm (0..=0.1).
    pub fiducial_edge_mm: f64,
    /// Fiducial diameter, mm (0.2..=5; a scene sets it with its top-level
    /// `fiducial_diameter_mm`).
    pub fiducial_diameter_mm: f64,
    /// Defects to inject.
    pub defects: DefectCounts,
    /// The print's own seed: the same deposits on every run of the scene (a repeatability
    /// study); absent, the run's seed prints a new board each time.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
}

impl Default for PrintParams {
    fn default() -> Self {
        PrintParams {
            stencil_um: 100.0,
            slump_mm: 0.02,
            edge_mm: 0.04,
            dog_ear_fraction: 0.2,
            dog_ear_height_um: 6.0,
            dog_ear_sigma_mm: 0.03,
            offset_sigma_mm: 0.01,
            offset_mm: None,
            rotation_mrad: 0.0,
            volume_pct: 0.0,
            clogging_pct: 0.0,
            clogging_area_ratio: DEFAULT_CLOGGING_AREA_RATIO,
            height_scatter_pct: 3.0,
            position_sigma_mm: 0.006,
            fiducial_height_um: 35.0,
            fiducial_edge_mm: 0.01,
            fiducial_diameter_mm: crate::array::layout::FIDUCIAL_DIAMETER_MM,
            defects: DefectCounts::default(),
            seed: None,
        }
    }
}

/// The area ratio below which an aperture clogs (`PrintParams::clogging_area_ratio`).
pub const DEFAULT_CLOGGING_AREA_RATIO: f64 = 0.8;

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

fn is_default_clogging_area_ratio(v: &f64) -> bool {
    *v == DEFAULT_CLOGGING_AREA_RATIO
}

/// Why a print cannot be made.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PrintError {
    /// A print parameter out of range (`knob` is its name under `print.`).
    #[error("invalid `print.{knob}`: {message}")]
    Param {
        /// The parameter's name, e.g. `stencil_um`.
        knob: String,
        /// The value found and the range expected.
        message: String,
    },
    /// A pad the print cannot fill.
    #[error("pad {pad}: {message}")]
    Pad {
        /// The pad's name (`component-pin` or `#index`).
        pad: String,
        /// What is wrong with its opening.
        message: String,
    },
    /// More defects than the layer can take.
    #[error("print.defects: {0}")]
    Defects(String),
}

impl PrintParams {
    /// Checks every parameter's range.
    pub fn validate(&self) -> Result<(), PrintError> {
        let range = |v: f64, lo: f64, hi: f64, knob: &str| {
            if v.is_finite() && (lo..=hi).contains(&v) {
                Ok(())
            } else {
                Err(PrintError::Param {
                    knob: knob.into(),
                    message: format!("{v}, expected a finite value in {lo}..={hi}"),
                })
            }
        };
        range(self.stencil_um, 50.0, 250.0, "stencil_um")?;
        range(self.slump_mm, 0.0, 0.1, "slump_mm")?;
        range(self.edge_mm, 0.0, 0.2, "edge_mm")?;
        range(self.dog_ear_fraction, 0.0, 1.0, "dog_ear_fraction")?;
        range(self.dog_ear_height_um, 0.0, 30.0, "dog_ear_height_um")?;
        range(self.dog_ear_sigma_mm, 0.005, 0.2, "dog_ear_sigma_mm")?;
        range(self.offset_sigma_mm, 0.0, 0.1, "offset_sigma_mm")?;
        range(self.height_scatter_pct, 0.0, 20.0, "height_scatter_pct")?;
        if let Some(o) = self.offset_mm {
            range(o[0], -0.5, 0.5, "offset_mm")?;
            range(o[1], -0.5, 0.5, "offset_mm")?;
        }
        range(self.rotation_mrad, -10.0, 10.0, "rotation_mrad")?;
        range(self.volume_pct, -50.0, 50.0, "volume_pct")?;
        range(self.clogging_pct, 0.0, 80.0, "clogging_pct")?;
        range(self.clogging_area_ratio, 0.3, 2.0, "clogging_area_ratio")?;
        range(self.position_sigma_mm, 0.0, 0.05, "position_sigma_mm")?;
        range(self.fiducial_height_um, 1.0, 200.0, "fiducial_height_um")?;
        range(self.fiducial_edge_mm, 0.0, 0.1, "fiducial_edge_mm")?;
        range(self.fiducial_diameter_mm, 0.2, 5.0, "fiducial_diameter_mm")?;
        Ok(())
    }
}

/// Area ratio of an opening: area / (perimeter x stencil thickness), both in mm.
pub fn area_ratio(outline: &Outline, stencil_um: f64) -> f64 {
    outline.area() / (outline.perimeter() * stencil_um * 1e-3)
}

/// Transfer efficiency (printed / opening volume) against the area ratio `AR`:
///
/// ```text
/// TE = 0.95                                          AR >= 0.8
///    = 0.75 + 0.20 smoothstep((AR - 0.5) / 0.3)      0.5 <= AR < 0.8
///    = max(0.70, 0.75 - 0.5 (0.5 - AR))              AR < 0.5
/// ```
///
/// Paste releases well from large openings (AR >= 0.8, the IPC-7525 guideline: ~95 %), less
/// as the walls' grip grows against the pad's area (about 75 % at AR 0.5), and is held at 70 %
/// below: every defect-free pad stays well inside a 50-150 % volume window.
pub fn transfer_efficiency(area_ratio: f64) -> f64 {
    if area_ratio >= 0.8 {
        0.95
    } else if area_ratio >= 0.5 {
        0.75 + 0.20 * smoothstep((area_ratio - 0.5) / 0.3)
    } else {
        (0.75 - 0.5 * (0.5 - area_ratio)).max(0.70)
    }
}

/// A defect class (or none).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Defect {
    /// No defect: the pad is printed normally.
    None,
    /// No paste at all.
    Missing,
    /// 15-50 % of the opening volume.
    Insufficient,
    /// 150-200 % of the opening volume, on a spread footprint.
    Excess,
    /// The normal volume shifted by 1/3 to 1/2 of the opening along x or y.
    Offset,
    /// Joined to its nearest neighbour by a paste strip.
    Bridge,
    /// The normal deposit plus a thin (15-30 um) smear beyond one side.
    Smear,
}

/// The truth of one printed pad.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrintedPad {
    /// Index of the pad in the layer.
    pub pad: usize,
    /// `component-pin` or `#index`.
    pub name: String,
    /// The defect injected on this pad ([`Defect::None`] if none).
    pub defect: Defect,
    /// The other pad of a bridge.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub partner: Option<usize>,
    /// Area ratio of the opening.
    pub area_ratio: f64,
    /// Transfer efficiency of the opening ([`transfer_efficiency`]).
    pub transfer_efficiency: f64,
    /// Volume of the pad's own deposits (main deposit, smear, dog-ears; not a bridge strip)
    /// over the opening volume (area x stencil thickness).
    pub volume_factor: f64,
    /// Plateau height of the main deposit, um (0 when missing).
    pub height_um: f64,
    /// Centroid of the main deposit's footprint minus the opening's centroid, design frame, mm
    /// (print offset + scatter + an offset defect; partial coverage moves it too).
    pub offset_mm: Point,
    /// The pad's own deposits (indices in [`Print::deposits`]).
    pub deposits: Vec<usize>,
    /// The bridge strip's deposit, for both pads of a bridge.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bridge: Option<usize>,
}

/// A fiducial as printed (copper, not paste).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrintedFiducial {
    /// Centre, design frame, mm.
    pub design: Point,
    /// Centre, board frame, mm.
    pub board: Point,
    /// Its deposit.
    pub deposit: usize,
}

/// A printed board: the deposits in the board frame and the truth per pad (`print.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Print {
    /// Design (paste layer) frame to board frame, mm.
    pub design_to_board: Rigid,
    /// The print offset drawn for this board, design frame, mm.
    pub print_offset_mm: Point,
    /// The print parameters used.
    pub params: PrintParams,
    /// The seed everything random in the print was drawn from.
    pub seed: u64,
    /// The identity of the board printed (`array.json`'s `board_id`, also in its map's
    /// `board.json`): `dpsa inspect` refuses the truth of another board. Absent in prints
    /// written before it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub board_id: Option<crate::simulation::recording::BoardId>,
    /// One per pad of the layer, in its order.
    pub pads: Vec<PrintedPad>,
    /// Everything on the board: pads' deposits, bridge strips, then fiducials.
    pub deposits: Vec<Deposit>,
    /// The copper fiducials, in the order given.
    pub fiducials: Vec<PrintedFiducial>,
}

impl Print {
    /// Opening volume of a pad (area x stencil thickness), um mm^2.
    pub fn opening_volume(&self, pad: &Pad) -> f64 {
        pad.outline.area() * self.params.stencil_um
    }

    /// Pads per defect class.
    pub fn count(&self, defect: Defect) -> usize {
        self.pads.iter().filter(|p| p.defect == defect).count()
    }
}

/// A standard normal truncated at +/-3.
pub(crate) fn normal3(rng: &mut impl rand::Rng) -> f64 {
    let z: f64 = StandardNormal.sample(rng);
    z.clamp(-3.0, 3.0)
}

/// Gap between two openings' boxes (exact for axis-aligned rectangles, and for two discs).
fn gap(a: &Outline, b: &Outline) -> f64 {
    if let (
        Outline::Circle {
            centre: ca,
            diameter: da,
        },
        Outline::Circle {
            centre: cb,
            diameter: db,
        },
    ) = (a, b)
    {
        return (ca[0] - cb[0]).hypot(ca[1] - cb[1]) - (da + db) / 2.0;
    }
    let (p, q) = (a.bbox(), b.bbox());
    let dx = (q[0] - p[2]).max(p[0] - q[2]).max(0.0);
    let dy = (q[1] - p[3]).max(p[1] - q[3]).max(0.0);
    dx.hypot(dy)
}

/// Largest gap between nearest neighbours that a bridge may span, mm.
pub const MAX_BRIDGE_GAP_MM: f64 = 0.5;

/// Nearest neighbour (smallest gap, then lowest index) of every pad within
/// [`MAX_BRIDGE_GAP_MM`], among the pads of another pin (the panes of a windowed thermal pad
/// share their pin: paste between them is no defect).
fn nearest_neighbours(pads: &[Pad]) -> Vec<Option<usize>> {
    let cell = 2.0;
    let mut grid: std::collections::HashMap<(i64, i64), Vec<usize>> = Default::default();
    let key = |x: f64, y: f64| ((x / cell).floor() as i64, (y / cell).floor() as i64);
    for (i, p) in pads.iter().enumerate() {
        let b = p.outline.bbox();
        let (i0, j0) = key(b[0], b[1]);
        let (i1, j1) = key(b[2], b[3]);
        for j in j0..=j1 {
            for ii in i0..=i1 {
                grid.entry((ii, j)).or_default().push(i);
            }
        }
    }
    pads.iter()
        .enumerate()
        .map(|(i, p)| {
            let b = p.outline.bbox();
            let m = MAX_BRIDGE_GAP_MM;
            let (i0, j0) = key(b[0] - m, b[1] - m);
            let (i1, j1) = key(b[2] + m, b[3] + m);
            let mut best: Option<(f64, usize)> = None;
            for j in j0..=j1 {
                for ii in i0..=i1 {
                    for &k in grid.get(&(ii, j)).map(Vec::as_slice).unwrap_or(&[]) {
                        let same_pin = p.component.is_some()
                            && p.pin.is_some()
                            && p.component == pads[k].component
                            && p.pin == pads[k].pin;
                        if k == i || same_pin {
                            continue;
                        }
                        let g = gap(&p.outline, &pads[k].outline);
                        if g <= m && best.is_none_or(|(bg, bk)| g < bg || (g == bg && k < bk)) {
                            best = Some((g, k));
                        }
                    }
                }
            }
            best.map(|(_, k)| k)
        })
        .collect()
}

/// Distance from `c` along the unit direction `u` to the outline's edge (bisection; `c`
/// inside), mm.
fn edge_along(o: &Outline, c: Point, u: Point, max: f64) -> f64 {
    let at = |t: f64| o.signed_distance([c[0] + t * u[0], c[1] + t * u[1]]);
    let (mut lo, mut hi) = (0.0, max);
    if at(hi) <= 0.0 {
        return hi;
    }
    for _ in 0..50 {
        let mid = (lo + hi) / 2.0;
        if at(mid) <= 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    lo
}

/// A design-frame deposit before it is moved onto the board.
struct Draft {
    outline: Outline,
    height_um: f64,
    edge_mm: f64,
    bumps: Vec<Bump>,
    material: Material,
    pad: Option<usize>,
}

impl Draft {
    fn on_board(self, t: &Rigid) -> Deposit {
        Deposit {
            outline: self.outline.transformed(t),
            height_um: self.height_um,
            edge_mm: self.edge_mm,
            bumps: self
                .bumps
                .into_iter()
                .map(|b| Bump {
                    centre: t.apply(b.centre),
                    ..b
                })
                .collect(),
            material: self.material,
            pad: self.pad,
        }
    }
}

/// The footprint's extent along design axis `k` (0 = x, 1 = y), mm.
fn extent(o: &Outline, k: usize) -> f64 {
    let b = o.bbox();
    b[k + 2] - b[k]
}

/// Part of an outline: a `c` fraction of it along design axis `k`, against side `sign`.
fn partial(o: &Outline, k: usize, c: f64, sign: f64) -> Option<Outline> {
    match o {
        Outline::Circle { centre, diameter } => {
            let d = diameter * c.sqrt();
            let mut centre = *centre;
            centre[k] += sign * (diameter - d) / 2.0;
            Some(Outline::Circle {
                centre,
                diameter: d,
            })
        }
        Outline::RoundRect {
            centre,
            size,
            radius,
            rotation_deg,
        } => {
            // The opening's own axis closest to design axis k.
            let (s, co) = rotation_deg.to_radians().sin_cos();
            let own = if (co.abs() >= s.abs()) == (k == 0) {
                0
            } else {
                1
            };
            let axis = if own == 0 { [co, s] } else { [-s, co] };
            let mut size = *size;
            let cut = size[own] * (1.0 - c);
            size[own] -= cut;
            let dir = if axis[k] >= 0.0 { sign } else { -sign };
            Some(Outline::RoundRect {
                centre: [
                    centre[0] + dir * axis[0] * cut / 2.0,
                    centre[1] + dir * axis[1] * cut / 2.0,
                ],
                size,
                radius: radius.min(size[0].min(size[1]) / 2.0),
                rotation_deg: *rotation_deg,
            })
        }
        Outline::Polygon { .. } => None,
    }
}

/// Dog-ears at the four corners of a rectangular deposit (design frame).
fn dog_ears(o: &Outline, p: &PrintParams, rng: &mut impl rand::Rng) -> Vec<Bump> {
    let Outline::RoundRect {
        centre,
        size,
        rotation_deg,
        ..
    } = o
    else {
        return Vec::new();
    };
    let (s, c) = rotation_deg.to_radians().sin_cos();
    let inset = p.edge_mm.max(p.dog_ear_sigma_mm);
    let (hu, hv) = (
        (size[0] / 2.0 - inset).max(size[0] / 4.0),
        (size[1] / 2.0 - inset).max(size[1] / 4.0),
    );
    [(1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0)]
        .into_iter()
        .map(|(a, b)| {
            let (u, v) = (a * hu, b * hv);
            Bump {
                centre: [centre[0] + c * u - s * v, centre[1] + s * u + c * v],
                sigma_mm: p.dog_ear_sigma_mm,
                height_um: p.dog_ear_height_um * rng.random_range(0.5..=1.0),
            }
        })
        .collect()
}

/// Prints `pads` (design frame, mm) and the copper `fiducials` (design frame) with `params`,
/// placed on the board by `design_to_board`; everything random is drawn from `seed`.
pub fn print(
    pads: &[Pad],
    fiducials: &[Point],
    params: &PrintParams,
    design_to_board: &Rigid,
    seed: u64,
) -> Result<Print, PrintError> {
    check_inputs(pads, params)?;
    let mut rng = crate::simulation::simulate::rng(seed, 0x7072_696e);
    let t_um = params.stencil_um;
    // Drawn always, so that a given offset leaves every other draw as it was.
    let drawn = [
        params.offset_sigma_mm * normal3(&mut rng),
        params.offset_sigma_mm * normal3(&mut rng),
    ];
    let offset = params.offset_mm.unwrap_or(drawn);
    let (defect, partner) = assign_defects(pads, &params.defects, &mut rng)?;
    // The turn moves each opening's deposit by `theta x` its distance from the pattern's
    // centre (mrad x mm = um).
    let turn = params.rotation_mrad * 1e-3;
    let centre = if turn == 0.0 || pads.is_empty() {
        [0.0; 2]
    } else {
        let n = pads.len() as f64;
        let c = pads.iter().map(|p| p.outline.centroid());
        c.fold([0.0; 2], |a, q| [a[0] + q[0] / n, a[1] + q[1] / n])
    };

    let mut drafts: Vec<Draft> = Vec::new();
    let mut printed: Vec<PrintedPad> = Vec::with_capacity(pads.len());
    for (i, pad) in pads.iter().enumerate() {
        let q = pad.outline.centroid();
        let at = if turn == 0.0 {
            offset
        } else {
            [
                offset[0] - turn * (q[1] - centre[1]),
                offset[1] + turn * (q[0] - centre[0]),
            ]
        };
        let (own, pp) = print_pad(i, pad, defect[i], at, params, &mut rng);
        let first = drafts.len();
        drafts.extend(own);
        printed.push(PrintedPad {
            partner: partner[i],
            deposits: (first..drafts.len()).collect(),
            ..pp
        });
    }
    bridge_strips(&partner, &mut printed, &mut drafts, params, &mut rng);
    let mut deposits: Vec<Deposit> = drafts
        .into_iter()
        .map(|d| d.on_board(design_to_board))
        .collect();
    for (pp, pad) in printed.iter_mut().zip(pads) {
        let v = pp
            .deposits
            .iter()
            .fold(0.0, |v, &k| v + deposits[k].volume());
        pp.volume_factor = v / (pad.outline.area() * t_um);
    }
    let fids = fiducial_deposits(fiducials, params, design_to_board, &mut deposits)?;
    Ok(Print {
        design_to_board: *design_to_board,
        print_offset_mm: offset,
        params: params.clone(),
        seed,
        board_id: None,
        pads: printed,
        deposits,
        fiducials: fids,
    })
}

/// The parameters in range, every outline sane, and enough pads for the defects asked for.
fn check_inputs(pads: &[Pad], params: &PrintParams) -> Result<(), PrintError> {
    params.validate()?;
    for p in pads {
        if !p.outline.is_sane() {
            return Err(PrintError::Pad {
                pad: p.name(),
                message: format!("degenerate outline {:?}", p.outline),
            });
        }
    }
    let want = params.defects.pads();
    if want > pads.len() as u64 {
        return Err(PrintError::Defects(format!(
            "{want} defective pads asked for (a bridge takes two), but the layer has {} pads",
            pads.len()
        )));
    }
    Ok(())
}

/// Which pad gets which defect (and each bridged pad's partner), in a random order: bridges
/// first (they need free nearest neighbours), then the others.
fn assign_defects(
    pads: &[Pad],
    d: &DefectCounts,
    rng: &mut impl rand::Rng,
) -> Result<(Vec<Defect>, Vec<Option<usize>>), PrintError> {
    let mut defect = vec![Defect::None; pads.len()];
    let mut partner: Vec<Option<usize>> = vec![None; pads.len()];
    let mut order: Vec<usize> = (0..pads.len()).collect();
    order.shuffle(rng);
    if d.bridge > 0 {
        let nn = nearest_neighbours(pads);
        let mut made = 0;
        for &i in &order {
            if made == d.bridge {
                break;
            }
            if let Some(j) = nn[i] {
                if defect[i] == Defect::None && defect[j] == Defect::None {
                    defect[i] = Defect::Bridge;
                    defect[j] = Defect::Bridge;
                    partner[i] = Some(j);
                    partner[j] = Some(i);
                    made += 1;
                }
            }
        }
        if made < d.bridge {
            return Err(PrintError::Defects(format!(
                "bridge = {}, but only {made} free pairs of nearest neighbours with a gap <= {MAX_BRIDGE_GAP_MM} mm",
                d.bridge
            )));
        }
    }
    let mut classes = Vec::new();
    for (n, c) in [
        (d.missing, Defect::Missing),
        (d.insufficient, Defect::Insufficient),
        (d.excess, Defect::Excess),
        (d.offset, Defect::Offset),
        (d.smear, Defect::Smear),
    ] {
        classes.extend(std::iter::repeat_n(c, n as usize));
    }
    let free: Vec<usize> = order
        .iter()
        .copied()
        .filter(|&i| defect[i] == Defect::None)
        .collect();
    // The count check of `check_inputs` guarantees enough free pads.
    for (c, i) in classes.into_iter().zip(free) {
        defect[i] = c;
    }
    Ok((defect, partner))
}

/// Pad `i`'s deposits (design frame; none when missing, a second one for a smear) and its
/// record, without `partner`, `deposits` and `volume_factor` (the caller's).
fn print_pad(
    i: usize,
    pad: &Pad,
    defect: Defect,
    offset: Point,
    params: &PrintParams,
    rng: &mut impl rand::Rng,
) -> (Vec<Draft>, PrintedPad) {
    let t_um = params.stencil_um;
    let o = &pad.outline;
    let ar = area_ratio(o, t_um);
    let te = transfer_efficiency(ar);
    let v_open = o.area() * t_um;
    let scatter_v = 1.0 + params.height_scatter_pct / 100.0 * normal3(rng);
    // The board's level and a clogged aperture's loss (exactly 1 when neither is set).
    let clogged = if ar < params.clogging_area_ratio {
        params.clogging_pct
    } else {
        0.0
    };
    let level = (1.0 + params.volume_pct / 100.0) * (1.0 - clogged / 100.0);
    let scatter_p = [
        params.position_sigma_mm * normal3(rng),
        params.position_sigma_mm * normal3(rng),
    ];
    let u: [f64; 6] = std::array::from_fn(|_| rng.random::<f64>());
    let slumped = o.offset(params.slump_mm).unwrap_or_else(|| o.clone());
    let mut shift = [offset[0] + scatter_p[0], offset[1] + scatter_p[1]];
    let mut own: Vec<Draft> = Vec::new();
    let mut volume = te * scatter_v * v_open * level;
    let mut footprint = slumped.clone();
    let mut ears = false;
    match defect {
        Defect::Missing => volume = 0.0,
        Defect::Insufficient => {
            volume = (0.15 + 0.35 * u[0]) * v_open;
            // Half of them cover only part of the opening (lower on the rest).
            if u[1] < 0.5 {
                let f = volume / v_open;
                let c = (f + 0.15).max(0.5) + u[2] * (0.85 - (f + 0.15).max(0.5));
                let k = usize::from(u[3] < 0.5);
                let sign = if u[4] < 0.5 { -1.0 } else { 1.0 };
                if let Some(part) = partial(o, k, c, sign) {
                    footprint = part.offset(params.slump_mm).unwrap_or(part);
                }
            }
        }
        Defect::Excess => {
            volume = (1.5 + 0.5 * u[0]) * v_open;
            let spread = 0.03 + 0.05 * u[1];
            footprint = o
                .offset(params.slump_mm + spread)
                .unwrap_or_else(|| o.clone());
        }
        Defect::Offset => {
            let k = usize::from(u[0] < 0.5);
            let sign = if u[1] < 0.5 { -1.0 } else { 1.0 };
            shift[k] += sign * (1.0 / 3.0 + u[2] / 6.0) * extent(o, k);
            ears = true;
        }
        Defect::None | Defect::Bridge | Defect::Smear => ears = true,
    }
    let c0 = o.centroid();
    let mut height = 0.0;
    let mut offset_mm = [0.0, 0.0];
    if volume > 0.0 {
        let fp = footprint.shifted(shift);
        let aeff = effective_area(&fp, params.edge_mm);
        height = volume / aeff;
        let is_rect = matches!(&fp, Outline::RoundRect { size, radius, .. }
            if *radius < 0.45 * size[0].min(size[1]));
        let bumps = if ears && is_rect && rng.random::<f64>() < params.dog_ear_fraction {
            dog_ears(&fp, params, rng)
        } else {
            Vec::new()
        };
        let c1 = fp.centroid();
        offset_mm = [c1[0] - c0[0], c1[1] - c0[1]];
        own.push(Draft {
            outline: fp,
            height_um: height,
            edge_mm: params.edge_mm,
            bumps,
            material: Material::Paste,
            pad: Some(i),
        });
    }
    if defect == Defect::Smear {
        if let Some(main) = own.first() {
            let smear = smear_draft(&main.outline, i, &u, params, rng);
            own.push(smear);
        }
    }
    let pp = PrintedPad {
        pad: i,
        name: pad.name(),
        defect,
        partner: None,
        area_ratio: ar,
        transfer_efficiency: te,
        volume_factor: 0.0,
        height_um: height,
        offset_mm,
        deposits: Vec::new(),
        bridge: None,
    };
    (own, pp)
}

/// The smear beside pad `i`'s deposit `main`: a low strip out of one side (`u`: the pad's
/// uniform draws, which side and how far).
fn smear_draft(
    main: &Outline,
    i: usize,
    u: &[f64; 6],
    params: &PrintParams,
    rng: &mut impl rand::Rng,
) -> Draft {
    let b = main.bbox();
    let k = usize::from(u[3] < 0.5);
    let across = 1 - k;
    let sign = if u[4] < 0.5 { -1.0 } else { 1.0 };
    let reach = (0.2 + 0.3 * u[5]) * (b[k + 2] - b[k]);
    let width = (0.6 + 0.3 * rng.random::<f64>()) * (b[across + 2] - b[across]);
    let e = params.edge_mm;
    let side = if sign > 0.0 { b[k + 2] } else { b[k] };
    let mut centre = [0.0; 2];
    centre[k] = side + sign * (reach - e) / 2.0;
    centre[across] = (b[across] + b[across + 2]) / 2.0;
    let mut size = [0.0; 2];
    size[k] = reach + e;
    size[across] = width;
    Draft {
        outline: Outline::RoundRect {
            centre,
            size,
            radius: 0.2 * size[0].min(size[1]),
            rotation_deg: 0.0,
        },
        height_um: 15.0 + 15.0 * rng.random::<f64>(),
        edge_mm: e,
        bumps: Vec::new(),
        material: Material::Paste,
        pad: Some(i),
    }
}

/// Bridge strips: from inside one deposit's wall to inside the other's, along the line
/// between their centroids, so the walls blend (smoothstep(u) + smoothstep(1 - u) = 1).
/// Appended to `drafts`; both pads' `bridge` set to it.
fn bridge_strips(
    partner: &[Option<usize>],
    printed: &mut [PrintedPad],
    drafts: &mut Vec<Draft>,
    params: &PrintParams,
    rng: &mut impl rand::Rng,
) {
    let t_um = params.stencil_um;
    for i in 0..partner.len() {
        let Some(j) = partner[i] else { continue };
        if j < i {
            continue;
        }
        let (Some(&da), Some(&db)) = (printed[i].deposits.first(), printed[j].deposits.first())
        else {
            continue;
        };
        let (a, b) = (&drafts[da].outline, &drafts[db].outline);
        let (ca, cb) = (a.centroid(), b.centroid());
        let len = (cb[0] - ca[0]).hypot(cb[1] - ca[1]);
        if len <= 0.0 {
            continue;
        }
        let dir = [(cb[0] - ca[0]) / len, (cb[1] - ca[1]) / len];
        let e = params.edge_mm;
        let ta = (edge_along(a, ca, dir, len) - e).max(0.0);
        let tb = (edge_along(b, cb, [-dir[0], -dir[1]], len) - e).max(0.0);
        let (p0, p1) = (ta, (len - tb).max(ta));
        let across = |o: &Outline| {
            let bb = o.bbox();
            dir[1].abs() * (bb[2] - bb[0]) + dir[0].abs() * (bb[3] - bb[1])
        };
        let width = (0.3 + 0.3 * rng.random::<f64>()) * across(a).min(across(b));
        let mid = (p0 + p1) / 2.0;
        let strip = Outline::RoundRect {
            centre: [ca[0] + mid * dir[0], ca[1] + mid * dir[1]],
            size: [(p1 - p0).max(e), width],
            radius: 0.25 * width,
            rotation_deg: dir[1].atan2(dir[0]).to_degrees(),
        };
        let k = drafts.len();
        drafts.push(Draft {
            outline: strip,
            height_um: t_um * (0.5 + 0.4 * rng.random::<f64>()),
            edge_mm: e,
            bumps: Vec::new(),
            material: Material::Paste,
            pad: None,
        });
        printed[i].bridge = Some(k);
        printed[j].bridge = Some(k);
    }
}

/// The copper fiducials (design frame) as board-frame deposits appended to `deposits`, and
/// their records.
fn fiducial_deposits(
    fiducials: &[Point],
    params: &PrintParams,
    design_to_board: &Rigid,
    deposits: &mut Vec<Deposit>,
) -> Result<Vec<PrintedFiducial>, PrintError> {
    let mut fids = Vec::with_capacity(fiducials.len());
    for &f in fiducials {
        if !(f[0].is_finite() && f[1].is_finite()) {
            return Err(PrintError::Param {
                knob: "fiducials".into(),
                message: format!("{f:?} is not a finite point"),
            });
        }
        let board = design_to_board.apply(f);
        fids.push(PrintedFiducial {
            design: f,
            board,
            deposit: deposits.len(),
        });
        deposits.push(Deposit {
            outline: Outline::Circle {
                centre: board,
                diameter: params.fiducial_diameter_mm,
            },
            height_um: params.fiducial_height_um,
            edge_mm: params.fiducial_edge_mm,
            bumps: Vec::new(),
            material: Material::Copper,
            pad: None,
        });
    }
    Ok(fids)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::array::layout::{generate, LayoutBoard};

    /// `\int height` over a deposit's box on a grid of `step`, um mm^2.
    fn integrate(d: &Deposit, step: f64) -> f64 {
        let b = d.reach_bbox();
        let (nx, ny) = (
            ((b[2] - b[0]) / step).ceil() as usize + 2,
            ((b[3] - b[1]) / step).ceil() as usize + 2,
        );
        let mut s = 0.0;
        for j in 0..ny {
            for i in 0..nx {
                s += d.height([
                    b[0] - step + (i as f64 + 0.5) * step,
                    b[1] - step + (j as f64 + 0.5) * step,
                ]);
            }
        }
        s * step * step
    }

    #[test]
    fn transfer_efficiency_curve() {
        assert_eq!(transfer_efficiency(0.8), 0.95);
        assert_eq!(transfer_efficiency(2.0), 0.95);
        assert!((transfer_efficiency(0.5) - 0.75).abs() < 1e-12);
        assert!((transfer_efficiency(0.65) - 0.85).abs() < 1e-12);
        assert_eq!(transfer_efficiency(0.1), 0.70);
        // Monotone, continuous, within 0.7..=0.95.
        let mut last = transfer_efficiency(0.0);
        for k in 0..=300 {
            let te = transfer_efficiency(f64::from(k) / 200.0);
            assert!((0.70..=0.95).contains(&te));
            assert!(te >= last && te - last < 0.01, "{k}");
            last = te;
        }
        // A 0.25 mm BGA opening in a 100 um stencil: AR 0.625.
        let o = Outline::Circle {
            centre: [0.0, 0.0],
            diameter: 0.25,
        };
        assert!((area_ratio(&o, 100.0) - 0.625).abs() < 1e-12);
    }

    #[test]
    fn effective_area_and_volume_are_exact() {
        let shapes = [
            Outline::Circle {
                centre: [1.0, 2.0],
                diameter: 0.29,
            },
            Outline::Circle {
                centre: [0.0, 0.0],
                diameter: 0.06,
            },
            Outline::RoundRect {
                centre: [0.0, 0.0],
                size: [0.54, 0.59],
                radius: 0.08,
                rotation_deg: 0.0,
            },
            Outline::RoundRect {
                centre: [3.0, -1.0],
                size: [0.29, 1.54],
                radius: 0.02,
                rotation_deg: 90.3,
            },
            Outline::RoundRect {
                centre: [0.0, 0.0],
                size: [0.1, 0.3],
                radius: 0.0,
                rotation_deg: 0.0,
            },
            Outline::Polygon {
                exterior: vec![[0.0, 0.0], [0.6, 0.0], [0.6, 0.4], [0.0, 0.4]],
                holes: vec![],
            },
        ];
        for o in shapes {
            for edge in [0.0, 0.03, 0.05, 0.2] {
                let d = Deposit {
                    outline: o.clone(),
                    height_um: 90.0,
                    edge_mm: edge,
                    bumps: vec![],
                    material: Material::Paste,
                    pad: None,
                };
                let num = integrate(&d, 0.001);
                let v = d.volume();
                assert!(
                    (num - v).abs() <= 2e-3 * v,
                    "{o:?} edge {edge}: {num} vs {v}"
                );
            }
        }
    }

    fn small() -> (Vec<Pad>, Vec<Point>) {
        let l = generate(LayoutBoard::Small);
        (l.pads, l.fiducials)
    }

    /// A print process's knobs: the given offset and turn move every deposit by exactly the
    /// shift and turn at its opening (no scatter), the board's level and a clogged aperture's
    /// loss scale its volume, and every other draw is the plain print's.
    #[test]
    fn a_set_offset_turn_level_and_clogging_print_as_set() {
        let (pads, fids) = small();
        // No scatter of position, no dog-ears (their volume is their own).
        let plain = PrintParams {
            position_sigma_mm: 0.0,
            dog_ear_fraction: 0.0,
            ..PrintParams::default()
        };
        let set = PrintParams {
            offset_mm: Some([0.06, -0.03]),
            rotation_mrad: 0.7,
            volume_pct: -8.0,
            clogging_pct: 20.0,
            ..plain.clone()
        };
        let t = Rigid {
            rotation_rad: 0.0,
            tx: 1.0,
            ty: 2.0,
        };
        let a = print(&pads, &fids, &plain, &t, 3).unwrap();
        let b = print(&pads, &fids, &set, &t, 3).unwrap();
        assert_eq!(b.print_offset_mm, [0.06, -0.03]);
        let n = pads.len() as f64;
        let centre = pads.iter().fold([0.0; 2], |s, p| {
            let c = p.outline.centroid();
            [s[0] + c[0] / n, s[1] + c[1] / n]
        });
        let mut clogged = 0;
        for ((pa, pb), pad) in a.pads.iter().zip(&b.pads).zip(&pads) {
            if pa.defect != Defect::None {
                continue;
            }
            let q = pad.outline.centroid();
            let want = [
                0.06 - 0.7e-3 * (q[1] - centre[1]),
                -0.03 + 0.7e-3 * (q[0] - centre[0]),
            ];
            // The plain print's own offset (its drawn one) taken off.
            for (k, w) in want.into_iter().enumerate() {
                let moved = pb.offset_mm[k] - (pa.offset_mm[k] - a.print_offset_mm[k]);
                assert!((moved - w).abs() < 1e-9, "{}: {moved} vs {w}", pb.name);
            }
            let loss = if pa.area_ratio < DEFAULT_CLOGGING_AREA_RATIO {
                clogged += 1;
                0.8
            } else {
                1.0
            };
            let ratio = pb.volume_factor / pa.volume_factor;
            assert!((ratio - 0.92 * loss).abs() < 1e-9, "{}: {ratio}", pb.name);
        }
        assert!(clogged > 0, "no fine aperture on the small board");
        assert!(set.validate().is_ok());
        for bad in [
            PrintParams {
                offset_mm: Some([0.6, 0.0]),
                ..plain.clone()
            },
            PrintParams {
                rotation_mrad: f64::NAN,
                ..plain.clone()
            },
            PrintParams {
                clogging_pct: 90.0,
                ..plain.clone()
            },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
    }

    #[test]
    fn printed_volume_is_the_factor_times_the_opening_volume() {
        let (pads, fids) = small();
        let params = PrintParams {
            dog_ear_fraction: 0.5,
            defects: DefectCounts {
                missing: 2,
                insufficient: 4,
                excess: 3,
                offset: 3,
                bridge: 2,
                smear: 3,
            },
            ..PrintParams::default()
        };
        let t = Rigid {
            rotation_rad: 0.002,
            tx: 0.3,
            ty: -0.2,
        };
        let pr = print(&pads, &fids, &params, &t, 7).unwrap();
        let mut with_ears = 0;
        for (pp, pad) in pr.pads.iter().zip(&pads) {
            let mut v = 0.0;
            for &k in &pp.deposits {
                let d = &pr.deposits[k];
                with_ears += usize::from(!d.bumps.is_empty());
                v += integrate(d, 0.002);
            }
            let want = pp.volume_factor * pr.opening_volume(pad);
            assert!(
                (v - want).abs() <= 0.01 * want.max(1e-9),
                "{}: {:?} {v} vs {want}",
                pp.name,
                pp.defect
            );
        }
        assert!(with_ears > 0);
        // Deposits are in the board frame: a defect-free pad's deposit sits where the
        // transform puts the opening (within the print offset and scatter).
        let pp = pr.pads.iter().find(|p| p.defect == Defect::None).unwrap();
        let c = t.apply(pads[pp.pad].outline.centroid());
        let dc = pr.deposits[pp.deposits[0]].outline.centroid();
        assert!((c[0] - dc[0]).hypot(c[1] - dc[1]) < 0.06);
        // Fiducials: copper, 1 mm, at the transformed design points.
        assert_eq!(pr.fiducials.len(), 3);
        for f in &pr.fiducials {
            let d = &pr.deposits[f.deposit];
            assert_eq!(d.material, Material::Copper);
            assert!((d.height(f.board) - 35.0).abs() < 1e-9);
            assert_eq!(f.board, t.apply(f.design));
        }
        // The index finds what a full sum finds.
        let index = DepositIndex::new(&pr.deposits);
        for k in 0..4000 {
            let p = [
                0.5 + 19.0 * f64::from(k % 80) / 80.0,
                0.5 + 12.9 * f64::from(k / 80) / 50.0,
            ];
            let full: f64 = pr.deposits.iter().map(|d| d.height(p)).sum();
            let (h, _) = paste_height(&pr.deposits, &index, p);
            assert!((h - full).abs() < 1e-9, "{p:?}");
        }
        // JSON round trip.
        // JSON round trip (serde_json reads floats to within an ulp, not always exactly).
        let json = serde_json::to_string(&pr).unwrap();
        let back: Print = serde_json::from_str(&json).unwrap();
        assert_eq!(back.pads.len(), pr.pads.len());
        assert_eq!(back.deposits.len(), pr.deposits.len());
        for (a, b) in back.pads.iter().zip(&pr.pads) {
            assert_eq!(
                (a.defect, a.partner, &a.deposits),
                (b.defect, b.partner, &b.deposits)
            );
            assert!((a.volume_factor - b.volume_factor).abs() < 1e-12);
        }
        for (a, b) in back.deposits.iter().zip(&pr.deposits) {
            let c = b.outline.centroid();
            assert!((a.height(c) - b.height(c)).abs() < 1e-9);
            assert_eq!(a.bumps.len(), b.bumps.len());
        }
    }

    #[test]
    fn defects_are_injected_as_asked() {
        let l = generate(LayoutBoard::Paper);
        let params = PrintParams {
            defects: DefectCounts {
                missing: 5,
                insufficient: 20,
                excess: 20,
                offset: 20,
                bridge: 10,
                smear: 20,
            },
            ..PrintParams::default()
        };
        let pr = print(&l.pads, &l.fiducials, &params, &Rigid::IDENTITY, 3).unwrap();
        assert_eq!(pr.count(Defect::Missing), 5);
        assert_eq!(pr.count(Defect::Insufficient), 20);
        assert_eq!(pr.count(Defect::Excess), 20);
        assert_eq!(pr.count(Defect::Offset), 20);
        assert_eq!(pr.count(Defect::Bridge), 20);
        assert_eq!(pr.count(Defect::Smear), 20);
        let te_window = |p: &PrintedPad| (0.6..=1.1).contains(&p.volume_factor);
        for p in &pr.pads {
            let pad = &l.pads[p.pad];
            match p.defect {
                Defect::None => {
                    assert!(te_window(p), "{} {}", p.name, p.volume_factor);
                    assert!(p.offset_mm[0].hypot(p.offset_mm[1]) < 0.1);
                }
                Defect::Missing => {
                    assert!(p.deposits.is_empty() && p.volume_factor == 0.0);
                }
                Defect::Insufficient => {
                    assert!(
                        (0.149..=0.501).contains(&p.volume_factor),
                        "{}",
                        p.volume_factor
                    );
                    assert!(p.height_um <= params.stencil_um * 1.05, "{}", p.height_um);
                }
                Defect::Excess => {
                    assert!(
                        (1.499..=2.001).contains(&p.volume_factor),
                        "{}",
                        p.volume_factor
                    );
                }
                Defect::Offset => {
                    assert!(te_window(p));
                    let b = pad.outline.bbox();
                    let (ex, ey) = (b[2] - b[0], b[3] - b[1]);
                    let (ox, oy) = (p.offset_mm[0].abs(), p.offset_mm[1].abs());
                    let along_x = ox / ex >= 0.3 && ox / ex <= 0.55;
                    let along_y = oy / ey >= 0.3 && oy / ey <= 0.55;
                    assert!(along_x || along_y, "{} {:?}", p.name, p.offset_mm);
                }
                Defect::Bridge => {
                    let q = &pr.pads[p.partner.unwrap()];
                    assert_eq!(q.partner, Some(p.pad));
                    let other = &l.pads[q.pad];
                    assert!(
                        pad.component != other.component || pad.pin != other.pin,
                        "{}: a bridge within one pin",
                        p.name
                    );
                    assert_eq!(q.bridge, p.bridge);
                    assert!(gap(&pad.outline, &l.pads[q.pad].outline) <= MAX_BRIDGE_GAP_MM);
                    let strip = &pr.deposits[p.bridge.unwrap()];
                    let h = strip.height_um / params.stencil_um;
                    assert!((0.5..=0.9).contains(&h), "{h}");
                    // The strip joins the two deposits: the height never drops to the board
                    // on the line between their centroids.
                    let index = DepositIndex::new(&pr.deposits);
                    let (a, b) = (
                        pr.deposits[p.deposits[0]].outline.centroid(),
                        pr.deposits[q.deposits[0]].outline.centroid(),
                    );
                    for s in 0..=100 {
                        let t = f64::from(s) / 100.0;
                        let x = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
                        let (hh, paste) = paste_height(&pr.deposits, &index, x);
                        assert!(paste && hh > 0.3 * params.stencil_um, "{} {t} {hh}", p.name);
                    }
                }
                Defect::Smear => {
                    assert_eq!(p.deposits.len(), 2);
                    let s = &pr.deposits[p.deposits[1]];
                    assert!((15.0..=30.0).contains(&s.height_um));
                    let (m, sb) = (pr.deposits[p.deposits[0]].reach_bbox(), s.reach_bbox());
                    let beyond = (sb[2] - m[2])
                        .max(m[0] - sb[0])
                        .max(sb[3] - m[3])
                        .max(m[1] - sb[1]);
                    let size = (m[2] - m[0]).max(m[3] - m[1]);
                    assert!(beyond >= 0.2 * (m[2] - m[0]).min(m[3] - m[1]) - 1e-9);
                    assert!(beyond <= 0.5 * size + 1e-9);
                }
            }
        }
        // Deterministic.
        let again = print(&l.pads, &l.fiducials, &params, &Rigid::IDENTITY, 3).unwrap();
        assert_eq!(again, pr);
    }

    #[test]
    fn absurd_parameters_are_refused() {
        let (pads, fids) = small();
        for (p, knob) in [
            (
                PrintParams {
                    stencil_um: 1000.0,
                    ..PrintParams::default()
                },
                "stencil_um",
            ),
            (
                PrintParams {
                    slump_mm: -0.1,
                    ..PrintParams::default()
                },
                "slump_mm",
            ),
            (
                PrintParams {
                    height_scatter_pct: f64::NAN,
                    ..PrintParams::default()
                },
                "height_scatter_pct",
            ),
        ] {
            match print(&pads, &fids, &p, &Rigid::IDENTITY, 1) {
                Err(PrintError::Param { knob: k, .. }) => assert_eq!(k, knob),
                other => panic!("{knob}: {other:?}"),
            }
        }
        let many = PrintParams {
            defects: DefectCounts {
                missing: pads.len() as u32,
                smear: 1,
                ..DefectCounts::default()
            },
            ..PrintParams::default()
        };
        assert!(matches!(
            print(&pads, &fids, &many, &Rigid::IDENTITY, 1),
            Err(PrintError::Defects(_))
        ));
    }
}
