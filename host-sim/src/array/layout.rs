//! Generated board layouts: realistic top paste layers the project makes itself.
//!
//! [`generate`] builds, deterministically, the paste openings of a populated board: chips
//! (0201, 0402, 0603, 0805), SOT-23, SOIC-8/16 (1.27 mm), QFN 4x4 and 5x5 (0.5 mm pitch, the
//! thermal pad windowed into a 2x2 or 3x3 grid of panes), 0.5 mm pitch QFPs, BGAs at 0.8 mm
//! (0.38 mm round openings) and 0.5 mm pitch (0.27 mm), and three fiducials (1.0 mm copper
//! discs: not paste openings, kept apart in [`Layout::fiducials`]). Components sit on the board
//! without overlapping (courtyards apart), some turned by 90 degrees, with their reference
//! designators and pin names in [`Pad::component`] and [`Pad::pin`].
//!
//! [`Layout::gerber`] writes the layer as Gerber X2 with the `gerber-types` crate: `%FSLAX46Y46*%`,
//! `%MOMM*%`, file attributes (`.GenerationSoftware,dpsa,...`, `.FileFunction,Paste,Top`), C / R /
//! O apertures and a `RoundRect` aperture macro for the rounded chip openings, `%TO.C%` / `%TO.P%`
//! object attributes on every flash (D03). Pads come in the file's order, so the index of a
//! pad is the index a Gerber reader gives it, and `Pad::aperture` names the D code.
//!
//! Two boards: [`LayoutBoard::Paper`], the paper's 220 x 168 mm board (about 5,800 openings),
//! and [`LayoutBoard::Small`], the 20 x 13.9 mm board of `scenes/array-small.toml` (about 200).
//! The shipped files `scenes/paper-board.paste.gbr` and `scenes/array-small.paste.gbr` are
//! these layouts; `dpsa layout --board paper|small --out FILE` writes them again, byte for byte.

use crate::inspection::pads::{Outline, Pad, Point};
use crate::{Result, SimError};
use rand::seq::SliceRandom;
use rand::RngExt;
use serde::Serialize;

/// Which generated board.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum LayoutBoard {
    /// The paper's board, 220 x 168 mm.
    Paper,
    /// The short board of `scenes/array-small.toml`, 20 x 13.9 mm.
    Small,
}

impl LayoutBoard {
    /// Both boards.
    pub const ALL: [LayoutBoard; 2] = [LayoutBoard::Paper, LayoutBoard::Small];

    /// `paper` or `small`.
    pub fn name(self) -> &'static str {
        match self {
            LayoutBoard::Paper => "paper",
            LayoutBoard::Small => "small",
        }
    }

    /// Parses `paper` or `small`.
    pub fn parse(s: &str) -> Result<LayoutBoard> {
        match s {
            "paper" => Ok(LayoutBoard::Paper),
            "small" => Ok(LayoutBoard::Small),
            _ => Err(SimError::Refused(format!(
                "unknown board {s:?}: expected `paper` or `small`"
            ))),
        }
    }

    /// The shipped file of this layout, relative to the repository's `scenes/`.
    pub fn shipped_file(self) -> &'static str {
        match self {
            LayoutBoard::Paper => "paper-board.paste.gbr",
            LayoutBoard::Small => "array-small.paste.gbr",
        }
    }

    /// Board size `[length along x, width along y]`, mm.
    pub fn size_mm(self) -> [f64; 2] {
        match self {
            LayoutBoard::Paper => [220.0, 168.0],
            LayoutBoard::Small => [20.0, 13.9],
        }
    }
}

/// A package family.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
pub enum Family {
    /// Two-terminal chip, imperial size 0201.
    Chip0201,
    /// Two-terminal chip, imperial size 0402.
    Chip0402,
    /// Two-terminal chip, imperial size 0603.
    Chip0603,
    /// Two-terminal chip, imperial size 0805.
    Chip0805,
    /// SOT-23, three pins.
    Sot23,
    /// SOIC-8, 1.27 mm pitch.
    Soic8,
    /// SOIC-16, 1.27 mm pitch.
    Soic16,
    /// QFN, 4 x 4 mm body, 24 pins at 0.5 mm pitch; thermal pad in 2 x 2 panes.
    Qfn4x4,
    /// QFN, 5 x 5 mm body, 32 pins at 0.5 mm pitch; thermal pad in 3 x 3 panes.
    Qfn5x5,
    /// LQFP-32, 5 x 5 mm body, 0.5 mm pitch.
    Qfp32,
    /// LQFP-64, 10 x 10 mm body, 0.5 mm pitch.
    Qfp64,
    /// LQFP-100, 14 x 14 mm body, 0.5 mm pitch.
    Qfp100,
    /// BGA, 0.8 mm pitch, 0.38 mm round openings; `n x n` balls.
    Bga08(u8),
    /// BGA, 0.5 mm pitch, 0.27 mm round openings; `n x n` balls.
    Bga05(u8),
}

impl Family {
    /// A short name, e.g. `0402`, `QFN-5x5`, `BGA-0.8-12x12`.
    pub fn name(self) -> String {
        match self {
            Family::Chip0201 => "0201".into(),
            Family::Chip0402 => "0402".into(),
            Family::Chip0603 => "0603".into(),
            Family::Chip0805 => "0805".into(),
            Family::Sot23 => "SOT-23".into(),
            Family::Soic8 => "SOIC-8".into(),
            Family::Soic16 => "SOIC-16".into(),
            Family::Qfn4x4 => "QFN-4x4".into(),
            Family::Qfn5x5 => "QFN-5x5".into(),
            Family::Qfp32 => "QFP-32".into(),
            Family::Qfp64 => "QFP-64".into(),
            Family::Qfp100 => "QFP-100".into(),
            Family::Bga08(n) => format!("BGA-0.8-{n}x{n}"),
            Family::Bga05(n) => format!("BGA-0.5-{n}x{n}"),
        }
    }

    /// Whether it is a two-terminal chip.
    pub fn is_chip(self) -> bool {
        matches!(
            self,
            Family::Chip0201 | Family::Chip0402 | Family::Chip0603 | Family::Chip0805
        )
    }

    /// Reference designator prefix.
    fn prefix(self) -> &'static str {
        match self {
            Family::Sot23 => "Q",
            f if f.is_chip() => "R",
            _ => "U",
        }
    }
}

/// The aperture shape of one opening (axis-aligned, before the component's rotation).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shape {
    /// Round opening (Gerber `C`), diameter.
    Circle(f64),
    /// Rectangle (Gerber `R`), `[x, y]`.
    Rect([f64; 2]),
    /// Obround (Gerber `O`), `[x, y]`.
    Obround([f64; 2]),
    /// Rectangle with rounded corners (the `RoundRect` macro), `[x, y]` and radius.
    RoundRect([f64; 2], f64),
}

impl Shape {
    /// Turned by 90 degrees.
    fn turned(self) -> Shape {
        match self {
            Shape::Circle(d) => Shape::Circle(d),
            Shape::Rect([a, b]) => Shape::Rect([b, a]),
            Shape::Obround([a, b]) => Shape::Obround([b, a]),
            Shape::RoundRect([a, b], r) => Shape::RoundRect([b, a], r),
        }
    }

    /// Half extents `[x, y]`.
    fn half(self) -> [f64; 2] {
        match self {
            Shape::Circle(d) => [d / 2.0, d / 2.0],
            Shape::Rect([a, b]) | Shape::Obround([a, b]) | Shape::RoundRect([a, b], _) => {
                [a / 2.0, b / 2.0]
            }
        }
    }

    /// The opening at `centre`.
    fn outline(self, centre: Point) -> Outline {
        match self {
            Shape::Circle(d) => Outline::Circle {
                centre,
                diameter: d,
            },
            Shape::Rect(size) => Outline::RoundRect {
                centre,
                size,
                radius: 0.0,
                rotation_deg: 0.0,
            },
            Shape::Obround(size) => Outline::RoundRect {
                centre,
                size,
                radius: size[0].min(size[1]) / 2.0,
                rotation_deg: 0.0,
            },
            Shape::RoundRect(size, radius) => Outline::RoundRect {
                centre,
                size,
                radius,
                rotation_deg: 0.0,
            },
        }
    }

    /// Identity of the aperture: kind and dimensions in nm.
    fn key(self) -> (u8, [i64; 3]) {
        let nm = |v: f64| (v * 1e6).round() as i64;
        match self {
            Shape::Circle(d) => (0, [nm(d), 0, 0]),
            Shape::Rect([a, b]) => (1, [nm(a), nm(b), 0]),
            Shape::Obround([a, b]) => (2, [nm(a), nm(b), 0]),
            Shape::RoundRect([a, b], r) => (3, [nm(a), nm(b), nm(r)]),
        }
    }
}

/// One opening of a footprint: pin name, shape, centre relative to the component, mm.
struct FootPad {
    pin: String,
    shape: Shape,
    at: Point,
}

fn two_terminal(shape: Shape, x: f64) -> Vec<FootPad> {
    vec![
        FootPad {
            pin: "1".into(),
            shape,
            at: [-x, 0.0],
        },
        FootPad {
            pin: "2".into(),
            shape,
            at: [x, 0.0],
        },
    ]
}

/// Dual row (SOIC): `per_side` pins at `pitch`, rows at `y = -/+ row`; pin 1 bottom left,
/// counting counter-clockwise.
fn dual_row(per_side: usize, pitch: f64, row: f64, shape: Shape) -> Vec<FootPad> {
    let span = (per_side - 1) as f64 * pitch / 2.0;
    let mut v = Vec::new();
    for i in 0..per_side {
        v.push(FootPad {
            pin: (i + 1).to_string(),
            shape,
            at: [-span + i as f64 * pitch, -row],
        });
    }
    for i in 0..per_side {
        v.push(FootPad {
            pin: (per_side + i + 1).to_string(),
            shape,
            at: [span - i as f64 * pitch, row],
        });
    }
    v
}

/// Quad rows (QFN, QFP): `per_side` pins at `pitch` on each side, rows at `-/+ row`; pad
/// `[across, along the row]` = `size` on the bottom and top sides, turned on the left and
/// right; pin 1 at the top of the left side, counting counter-clockwise.
fn quad(per_side: usize, pitch: f64, row: f64, size: [f64; 2]) -> Vec<FootPad> {
    let span = (per_side - 1) as f64 * pitch / 2.0;
    let horizontal = Shape::Rect(size);
    let vertical = horizontal.turned();
    let mut v = Vec::new();
    let mut pin = 1;
    let mut push = |shape: Shape, at: Point| {
        v.push(FootPad {
            pin: pin.to_string(),
            shape,
            at,
        });
        pin += 1;
    };
    for i in 0..per_side {
        push(vertical, [-row, span - i as f64 * pitch]);
    }
    for i in 0..per_side {
        push(horizontal, [-span + i as f64 * pitch, -row]);
    }
    for i in 0..per_side {
        push(vertical, [row, -span + i as f64 * pitch]);
    }
    for i in 0..per_side {
        push(horizontal, [span - i as f64 * pitch, row]);
    }
    v
}

/// An exposed pad of `panes x panes` square windows of `pane` mm at `pitch`, all named `pin`.
fn thermal(panes: usize, pane: f64, pitch: f64, pin: usize) -> Vec<FootPad> {
    let span = (panes - 1) as f64 * pitch / 2.0;
    let mut v = Vec::new();
    for j in 0..panes {
        for i in 0..panes {
            v.push(FootPad {
                pin: pin.to_string(),
                shape: Shape::Rect([pane, pane]),
                at: [-span + i as f64 * pitch, span - j as f64 * pitch],
            });
        }
    }
    v
}

/// JEDEC ball row letters (no I, O, Q, S, X, Z).
fn ball_row(i: usize) -> String {
    const L: &[u8] = b"ABCDEFGHJKLMNPRTUVWY";
    if i < L.len() {
        (L[i] as char).to_string()
    } else {
        format!("A{}", L[i - L.len()] as char)
    }
}

fn grid(n: usize, pitch: f64, d: f64) -> Vec<FootPad> {
    let span = (n - 1) as f64 * pitch / 2.0;
    let mut v = Vec::new();
    for r in 0..n {
        for c in 0..n {
            v.push(FootPad {
                pin: format!("{}{}", ball_row(r), c + 1),
                shape: Shape::Circle(d),
                at: [-span + c as f64 * pitch, span - r as f64 * pitch],
            });
        }
    }
    v
}

/// The openings of a family (component at the origin, not turned).
fn footprint(f: Family) -> Vec<FootPad> {
    match f {
        Family::Chip0201 => two_terminal(Shape::RoundRect([0.30, 0.30], 0.05), 0.28),
        Family::Chip0402 => two_terminal(Shape::RoundRect([0.50, 0.55], 0.06), 0.48),
        Family::Chip0603 => two_terminal(Shape::RoundRect([0.80, 0.90], 0.08), 0.80),
        Family::Chip0805 => two_terminal(Shape::RoundRect([1.00, 1.30], 0.10), 0.95),
        Family::Sot23 => {
            let s = Shape::Rect([0.80, 0.90]);
            vec![
                FootPad {
                    pin: "1".into(),
                    shape: s,
                    at: [-0.95, -1.0],
                },
                FootPad {
                    pin: "2".into(),
                    shape: s,
                    at: [0.95, -1.0],
                },
                FootPad {
                    pin: "3".into(),
                    shape: s,
                    at: [0.0, 1.0],
                },
            ]
        }
        Family::Soic8 => dual_row(4, 1.27, 2.7, Shape::Obround([0.60, 1.50])),
        Family::Soic16 => dual_row(8, 1.27, 2.7, Shape::Obround([0.60, 1.50])),
        Family::Qfn4x4 => {
            let mut v = quad(6, 0.5, 1.95, [0.25, 0.70]);
            v.extend(thermal(2, 1.1, 1.3, 25));
            v
        }
        Family::Qfn5x5 => {
            let mut v = quad(8, 0.5, 2.45, [0.25, 0.70]);
            v.extend(thermal(3, 0.9, 1.1, 33));
            v
        }
        Family::Qfp32 => quad(8, 0.5, 3.35, [0.25, 1.20]),
        Family::Qfp64 => quad(16, 0.5, 5.75, [0.25, 1.50]),
        Family::Qfp100 => quad(25, 0.5, 7.75, [0.25, 1.50]),
        Family::Bga08(n) => grid(usize::from(n), 0.8, 0.38),
        Family::Bga05(n) => grid(usize::from(n), 0.5, 0.27),
    }
}

/// A placed component.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Component {
    /// Reference designator, e.g. `U3`.
    pub refdes: String,
    /// Package family.
    pub family: Family,
    /// Centre, mm (design frame).
    pub centre: Point,
    /// 0 or 90 degrees.
    pub rotation_deg: f64,
    /// Its pads: `pads[first_pad..first_pad + pad_count]`.
    pub first_pad: usize,
    /// Number of its pads (openings) in the layer.
    pub pad_count: usize,
}

/// A generated paste layer.
#[derive(Clone, Debug)]
pub struct Layout {
    /// Which generated board.
    pub board: LayoutBoard,
    /// Board length along x, mm.
    pub length_mm: f64,
    /// Board width along y, mm.
    pub width_mm: f64,
    /// Paste openings, in file order (`Pad::index` = position).
    pub pads: Vec<Pad>,
    /// Fiducial centres (1.0 mm copper discs, not paste openings), mm.
    pub fiducials: Vec<Point>,
    /// The placed components, in the order of their pads.
    pub components: Vec<Component>,
    /// The apertures: D code and shape, in the order of first use.
    pub apertures: Vec<(i32, Shape)>,
}

/// Diameter of the fiducials, mm.
pub const FIDUCIAL_DIAMETER_MM: f64 = 1.0;
/// Least distance between an opening and the board edge, mm.
pub const EDGE_CLEARANCE_MM: f64 = 0.5;

/// Rounds to 1 nm (what `%FSLAX46Y46*%` writes), so that the pads and the file agree exactly.
fn snap(v: f64) -> f64 {
    (v * 1e6).round() / 1e6
}

/// Axis-aligned rectangle `[x0, y0, x1, y1]`.
type Rect = [f64; 4];

fn overlaps(a: &Rect, b: &Rect) -> bool {
    a[0] < b[2] && b[0] < a[2] && a[1] < b[3] && b[1] < a[3]
}

/// Occupied courtyards in 5 mm buckets.
struct Occupancy {
    rects: Vec<Rect>,
    cell: f64,
    nx: usize,
    ny: usize,
    buckets: Vec<Vec<usize>>,
}

impl Occupancy {
    fn new(length: f64, width: f64) -> Self {
        let cell = 5.0;
        let nx = (length / cell).ceil() as usize + 1;
        let ny = (width / cell).ceil() as usize + 1;
        Occupancy {
            rects: Vec::new(),
            cell,
            nx,
            ny,
            buckets: vec![Vec::new(); nx * ny],
        }
    }

    fn range(&self, r: &Rect) -> (usize, usize, usize, usize) {
        let ix = |v: f64| ((v / self.cell).floor().max(0.0) as usize).min(self.nx - 1);
        let iy = |v: f64| ((v / self.cell).floor().max(0.0) as usize).min(self.ny - 1);
        (ix(r[0]), ix(r[2]), iy(r[1]), iy(r[3]))
    }

    /// The first occupied rectangle `r` overlaps, if any.
    fn hit(&self, r: &Rect) -> Option<&Rect> {
        let (x0, x1, y0, y1) = self.range(r);
        for j in y0..=y1 {
            for i in x0..=x1 {
                for &k in &self.buckets[j * self.nx + i] {
                    if overlaps(&self.rects[k], r) {
                        return Some(&self.rects[k]);
                    }
                }
            }
        }
        None
    }

    fn add(&mut self, r: Rect) {
        let k = self.rects.len();
        let (x0, x1, y0, y1) = self.range(&r);
        for j in y0..=y1 {
            for i in x0..=x1 {
                self.buckets[j * self.nx + i].push(k);
            }
        }
        self.rects.push(r);
    }
}

/// What to place: `count` groups of `group` identical components side by side.
struct Order {
    family: Family,
    count: usize,
    /// Components per group (chips come in rows, like resistor banks); `(min, max)`.
    group: (usize, usize),
    /// Best effort: dropped when the board is full (the small board's fillers).
    optional: bool,
}

fn order(family: Family, count: usize, group: (usize, usize), optional: bool) -> Order {
    Order {
        family,
        count,
        group,
        optional,
    }
}

/// Courtyard margin around a component's openings, mm (`tight`: the small board).
fn margin(f: Family, tight: bool) -> f64 {
    if f.is_chip() || tight {
        0.15
    } else {
        0.3
    }
}

/// What a board is made of: the component orders (placed in this order), the fiducials'
/// inset and keep-out (mm), the random seed and whether components are spread over the
/// board (the paper board) or packed (the small board).
struct Plan {
    orders: Vec<Order>,
    fid_inset: f64,
    keepout: f64,
    seed: u64,
    spread: bool,
}

fn plan(board: LayoutBoard) -> Plan {
    let (orders, fid_inset, keepout, seed, spread) = match board {
        LayoutBoard::Paper => (
            vec![
                order(Family::Qfp100, 4, (1, 1), false),
                order(Family::Qfp64, 6, (1, 1), false),
                order(Family::Bga08(12), 4, (1, 1), false),
                order(Family::Bga05(11), 4, (1, 1), false),
                order(Family::Soic16, 16, (1, 2), false),
                order(Family::Soic8, 24, (1, 3), false),
                order(Family::Qfn5x5, 10, (1, 1), false),
                order(Family::Qfn4x4, 12, (1, 2), false),
                order(Family::Sot23, 50, (1, 3), false),
                order(Family::Chip0805, 150, (1, 4), false),
                order(Family::Chip0603, 300, (1, 6), false),
                order(Family::Chip0402, 600, (1, 8), false),
                order(Family::Chip0201, 250, (1, 8), false),
            ],
            2.5,
            3.0,
            0x5041_5045_u64,
            true,
        ),
        LayoutBoard::Small => (
            vec![
                order(Family::Qfp32, 1, (1, 1), false),
                order(Family::Soic8, 1, (1, 1), false),
                order(Family::Qfn4x4, 1, (1, 1), false),
                order(Family::Bga08(5), 1, (1, 1), false),
                order(Family::Bga05(6), 1, (1, 1), false),
                order(Family::Sot23, 2, (1, 1), false),
                order(Family::Chip0805, 2, (1, 1), false),
                order(Family::Chip0603, 2, (1, 2), false),
                order(Family::Chip0402, 4, (1, 2), false),
                order(Family::Chip0201, 4, (1, 2), false),
                order(Family::Qfn5x5, 1, (1, 1), true),
                order(Family::Chip0603, 4, (1, 2), true),
                order(Family::Chip0402, 16, (1, 2), true),
                order(Family::Chip0201, 16, (1, 2), true),
            ],
            1.0,
            0.9,
            0x534d_414c_u64,
            false,
        ),
    };
    Plan {
        orders,
        fid_inset,
        keepout,
        seed,
        spread,
    }
}

/// Candidate lower-left corners: a 1 mm grid for a spread board (the caller shuffles it), a
/// row-major 0.25 mm scan for a packed one, `edge` mm clear of the board's edges.
fn anchors(length: f64, width: f64, edge: f64, spread: bool) -> Vec<Point> {
    let step = if spread { 1.0 } else { 0.25 };
    let nx = ((length - 2.0 * edge) / step).floor() as usize + 1;
    let ny = ((width - 2.0 * edge) / step).floor() as usize + 1;
    (0..ny)
        .flat_map(|j| (0..nx).map(move |i| [edge + i as f64 * step, edge + j as f64 * step]))
        .collect()
}

/// Half the courtyard of one component about its centre (its openings plus `m` mm).
fn courtyard_half(fp: &[FootPad], m: f64) -> [f64; 2] {
    let mut half = [0.0f64, 0.0f64];
    for p in fp {
        let h = p.shape.half();
        half[0] = half[0].max(p.at[0].abs() + h[0] + m);
        half[1] = half[1].max(p.at[1].abs() + h[1] + m);
    }
    half
}

/// The first free rectangle of `size` at an anchor, from anchor `start` on (wrapping), inside
/// the board less `edge`.
fn find_room(
    anchors: &[Point],
    start: usize,
    size: [f64; 2],
    occ: &Occupancy,
    board_mm: [f64; 2],
    edge: f64,
) -> Option<Rect> {
    for t in 0..anchors.len() {
        let a = anchors[(start + t) % anchors.len()];
        let r = [a[0], a[1], a[0] + size[0], a[1] + size[1]];
        if r[2] > board_mm[0] - edge || r[3] > board_mm[1] - edge {
            continue;
        }
        if occ.hit(&r).is_none() {
            return Some(r);
        }
    }
    None
}

/// The layout's pads, components and apertures as components are added.
#[derive(Default)]
struct Parts {
    /// Components per reference-designator prefix.
    counters: std::collections::BTreeMap<&'static str, usize>,
    pads: Vec<Pad>,
    components: Vec<Component>,
    apertures: Vec<(i32, Shape)>,
}

impl Parts {
    /// One component of `family` with openings `fp` centred on `centre` (a chip's prefix, C or
    /// R, drawn from `rng`); its openings become pads, with a new aperture per new shape.
    fn add(
        &mut self,
        family: Family,
        fp: &[FootPad],
        centre: Point,
        turned: bool,
        rng: &mut impl rand::Rng,
    ) {
        let prefix = if family.is_chip() {
            if rng.random_range(0..2) == 0 {
                "C"
            } else {
                "R"
            }
        } else {
            family.prefix()
        };
        let n = self.counters.entry(prefix).or_insert(0);
        *n += 1;
        let refdes = format!("{prefix}{n}");
        let first = self.pads.len();
        for p in fp {
            let code = match self
                .apertures
                .iter()
                .find(|(_, s)| s.key() == p.shape.key())
            {
                Some(&(code, _)) => code,
                None => {
                    let code = 10 + self.apertures.len() as i32;
                    self.apertures.push((code, p.shape));
                    code
                }
            };
            let at = [snap(centre[0] + p.at[0]), snap(centre[1] + p.at[1])];
            self.pads.push(Pad {
                index: self.pads.len(),
                outline: p.shape.outline(at),
                component: Some(refdes.clone()),
                pin: Some(p.pin.clone()),
                aperture: Some(format!("D{code}")),
            });
        }
        self.components.push(Component {
            refdes,
            family,
            centre,
            rotation_deg: if turned { 90.0 } else { 0.0 },
            first_pad: first,
            pad_count: fp.len(),
        });
    }
}

/// Generates a board's layout (deterministic: the same every time, on every machine).
pub fn generate(board: LayoutBoard) -> Layout {
    let [length, width] = board.size_mm();
    let Plan {
        orders,
        fid_inset,
        keepout,
        seed,
        spread,
    } = plan(board);
    let mut rng = crate::simulation::simulate::rng(seed, 0x1a70);
    let fiducials: Vec<Point> = vec![
        [fid_inset, fid_inset],
        [length - fid_inset, fid_inset],
        [fid_inset, width - fid_inset],
    ];
    let mut occ = Occupancy::new(length, width);
    for f in &fiducials {
        occ.add([
            f[0] - keepout,
            f[1] - keepout,
            f[0] + keepout,
            f[1] + keepout,
        ]);
    }
    // A shuffled 1 mm grid spreads the paper board's components over the whole board; a
    // row-major 0.25 mm scan packs the small board. The paper board keeps 1.5 mm clear of its
    // edges, so that the board's placement error on the conveyor (`[placement]`, up to 3
    // sigma) cannot push an opening off it.
    let edge = match board {
        LayoutBoard::Paper => 1.5,
        LayoutBoard::Small => EDGE_CLEARANCE_MM,
    };
    let mut anchors = anchors(length, width, edge, spread);
    if spread {
        anchors.shuffle(&mut rng);
    }
    let mut parts = Parts::default();
    for o in &orders {
        let mut left = o.count;
        while left > 0 {
            let k = rng.random_range(o.group.0..=o.group.1).min(left);
            left -= k;
            let turned = rng.random_range(0..10) < 3;
            let mut fp = footprint(o.family);
            if turned {
                for p in &mut fp {
                    p.shape = p.shape.turned();
                    p.at = [-p.at[1], p.at[0]];
                }
            }
            let half = courtyard_half(&fp, margin(o.family, !spread));
            // A group runs along x for unturned chips, along y for turned ones.
            let along = usize::from(turned);
            let mut size = [2.0 * half[0], 2.0 * half[1]];
            size[along] *= k as f64;
            let start = if spread {
                rng.random_range(0..anchors.len())
            } else {
                0
            };
            let Some(r) = find_room(&anchors, start, size, &occ, [length, width], edge) else {
                assert!(
                    o.optional,
                    "internal error: layout {}: no room for {} x {}",
                    board.name(),
                    k,
                    o.family.name()
                );
                continue;
            };
            occ.add(r);
            for c in 0..k {
                let mut centre = [r[0] + half[0], r[1] + half[1]];
                centre[along] += c as f64 * 2.0 * half[along];
                let centre = [snap(centre[0]), snap(centre[1])];
                parts.add(o.family, &fp, centre, turned, &mut rng);
            }
        }
    }
    Layout {
        board,
        length_mm: length,
        width_mm: width,
        pads: parts.pads,
        fiducials,
        components: parts.components,
        apertures: parts.apertures,
    }
}

/// Pads and components of one family on a layout.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FamilyCount {
    /// The family's short name ([`Family::name`]).
    pub family: String,
    /// Components of the family.
    pub components: usize,
    /// Paste openings of those components.
    pub pads: usize,
}

impl Layout {
    /// Components and pads per family, in family order.
    pub fn family_counts(&self) -> Vec<FamilyCount> {
        let mut m: std::collections::BTreeMap<Family, (usize, usize)> = Default::default();
        for c in &self.components {
            let e = m.entry(c.family).or_insert((0, 0));
            e.0 += 1;
            e.1 += c.pad_count;
        }
        m.into_iter()
            .map(|(f, (components, pads))| FamilyCount {
                family: f.name(),
                components,
                pads,
            })
            .collect()
    }

    /// The layer as Gerber X2 (see the module docs).
    pub fn gerber(&self) -> Result<Vec<u8>> {
        use gerber_types::{
            Aperture, ApertureDefinition, ApertureMacro, AttributeDeletionCriterion,
            CenterLinePrimitive, Circle, CirclePrimitive, Command, CommentContent,
            CoordinateFormat, CoordinateMode, CoordinateNumber, Coordinates, DCode, ExtendedCode,
            FileAttribute, FileFunction, FilePolarity, FunctionCode, GCode, GenerationSoftware,
            GerberCode, MCode, MacroDecimal, ObjectAttribute, Operation, Part, Pin, Polarity,
            Position, Rectangular, Unit, ZeroOmission,
        };
        let cf = CoordinateFormat::new(ZeroOmission::Leading, CoordinateMode::Absolute, 4, 6);
        let comment = |s: String| -> Command {
            FunctionCode::GCode(GCode::Comment(CommentContent::String(s))).into()
        };
        let mut cmds: Vec<Command> = vec![
            comment(format!(
                "dpsa generated top paste layer: board {}, {} x {} mm, {} openings",
                self.board.name(),
                self.length_mm,
                self.width_mm,
                self.pads.len()
            )),
            comment(format!(
                "regenerate with: dpsa layout --board {} --out FILE",
                self.board.name()
            )),
            ExtendedCode::FileAttribute(FileAttribute::GenerationSoftware(
                GenerationSoftware::new("dpsa", "dpsa-layout", Some("1")),
            ))
            .into(),
            ExtendedCode::FileAttribute(FileAttribute::Part(Part::Single)).into(),
            ExtendedCode::FileAttribute(FileAttribute::FileFunction(FileFunction::Paste(
                Position::Top,
            )))
            .into(),
            ExtendedCode::FileAttribute(FileAttribute::FilePolarity(FilePolarity::Positive)).into(),
            ExtendedCode::CoordinateFormat(cf).into(),
            ExtendedCode::Unit(Unit::Millimeters).into(),
        ];
        let expr = |s: &str| MacroDecimal::Expression(s.into());
        let v = MacroDecimal::Value;
        if self
            .apertures
            .iter()
            .any(|(_, s)| matches!(s, Shape::RoundRect(..)))
        {
            // $1 x $2 rectangle, corners rounded with radius $3, centred, axis-aligned: two
            // overlapping centre-line rectangles and four corner discs.
            let circle = |x: &str, y: &str| {
                CirclePrimitive::new(expr("$3+$3")).centered_at((expr(x), expr(y)))
            };
            let am = ApertureMacro::new("RoundRect")
                .add_content(
                    "Rectangle with rounded corners: $1 width, $2 height, $3 corner radius",
                )
                .add_content(CenterLinePrimitive {
                    exposure: gerber_types::MacroBoolean::Value(true),
                    dimensions: (MacroDecimal::Variable(1), expr("$2-$3-$3")),
                    center: (v(0.0), v(0.0)),
                    angle: v(0.0),
                })
                .add_content(CenterLinePrimitive {
                    exposure: gerber_types::MacroBoolean::Value(true),
                    dimensions: (expr("$1-$3-$3"), MacroDecimal::Variable(2)),
                    center: (v(0.0), v(0.0)),
                    angle: v(0.0),
                })
                .add_content(circle("$1/2-$3", "$2/2-$3"))
                .add_content(circle("$3-$1/2", "$2/2-$3"))
                .add_content(circle("$3-$1/2", "$3-$2/2"))
                .add_content(circle("$1/2-$3", "$3-$2/2"));
            cmds.push(ExtendedCode::ApertureMacro(am).into());
        }
        for &(code, shape) in &self.apertures {
            let aperture = match shape {
                Shape::Circle(d) => Aperture::Circle(Circle::new(snap(d))),
                Shape::Rect([a, b]) => Aperture::Rectangle(Rectangular::new(snap(a), snap(b))),
                Shape::Obround([a, b]) => Aperture::Obround(Rectangular::new(snap(a), snap(b))),
                Shape::RoundRect([a, b], r) => Aperture::Macro(
                    "RoundRect".into(),
                    Some(vec![v(snap(a)), v(snap(b)), v(snap(r))]),
                ),
            };
            cmds.push(
                ExtendedCode::ApertureDefinition(ApertureDefinition::new(code, aperture)).into(),
            );
        }
        cmds.push(ExtendedCode::LoadPolarity(Polarity::Dark).into());
        let nm = |mm: f64| -> Result<CoordinateNumber> {
            if !(mm.is_finite() && mm.abs() < 9999.0) {
                return Err(SimError::Refused(format!(
                    "coordinate {mm} mm out of range"
                )));
            }
            Ok(CoordinateNumber::new((mm * 1e6).round() as i64))
        };
        let mut current: Option<&str> = None;
        for c in &self.components {
            cmds.push(
                ExtendedCode::ObjectAttribute(ObjectAttribute::Component(c.refdes.clone())).into(),
            );
            for p in &self.pads[c.first_pad..c.first_pad + c.pad_count] {
                let code = p
                    .aperture
                    .as_deref()
                    .ok_or_else(|| SimError::Internal("pad without aperture".into()))?;
                if current != Some(code) {
                    let n: i32 = code
                        .trim_start_matches('D')
                        .parse()
                        .map_err(|e| SimError::Internal(format!("aperture name: {e}")))?;
                    cmds.push(FunctionCode::DCode(DCode::SelectAperture(n)).into());
                    current = Some(code);
                }
                cmds.push(
                    ExtendedCode::ObjectAttribute(ObjectAttribute::Pin(Pin {
                        refdes: c.refdes.clone(),
                        name: p.pin.clone().unwrap_or_default(),
                        function: None,
                    }))
                    .into(),
                );
                let at = p.outline.centroid();
                cmds.push(
                    FunctionCode::DCode(DCode::Operation(Operation::Flash(Some(
                        Coordinates::new(nm(at[0])?, nm(at[1])?, cf),
                    ))))
                    .into(),
                );
            }
            cmds.push(
                ExtendedCode::DeleteAttribute(
                    AttributeDeletionCriterion::AllApertureAndObjectAttributes,
                )
                .into(),
            );
        }
        cmds.push(FunctionCode::MCode(MCode::EndOfFile).into());
        let mut out = Vec::new();
        cmds.serialize(&mut out)
            .map_err(|e| SimError::Refused(format!("writing the Gerber layer: {e}")))?;
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn scenes() -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes")
    }

    #[test]
    fn layouts_have_the_promised_families_and_counts() {
        for board in LayoutBoard::ALL {
            let l = generate(board);
            let counts = l.family_counts();
            let n = l.pads.len();
            let families: Vec<&str> = counts.iter().map(|c| c.family.as_str()).collect();
            for f in [
                "0201", "0402", "0603", "0805", "SOT-23", "SOIC-8", "QFN-4x4",
            ] {
                assert!(families.contains(&f), "{board:?}: no {f}: {counts:?}");
            }
            assert!(families.iter().any(|f| f.starts_with("QFP")), "{counts:?}");
            assert!(
                families.iter().any(|f| f.starts_with("BGA-0.8")),
                "{counts:?}"
            );
            assert!(
                families.iter().any(|f| f.starts_with("BGA-0.5")),
                "{counts:?}"
            );
            match board {
                LayoutBoard::Paper => {
                    assert!((4000..=8000).contains(&n), "{n}");
                    for f in ["SOIC-16", "QFN-5x5", "QFP-64", "QFP-100"] {
                        assert!(families.contains(&f), "{f}: {counts:?}");
                    }
                }
                LayoutBoard::Small => assert!((150..=300).contains(&n), "{n}"),
            }
            assert_eq!(l.fiducials.len(), 3);
            // Some components turned, names kept.
            assert!(l.components.iter().any(|c| c.rotation_deg == 90.0));
            assert!(l
                .pads
                .iter()
                .all(|p| p.component.is_some() && p.pin.is_some()));
            for (i, p) in l.pads.iter().enumerate() {
                assert_eq!(p.index, i);
            }
        }
    }

    #[test]
    fn openings_do_not_overlap_and_stay_on_the_board() {
        for board in LayoutBoard::ALL {
            let l = generate(board);
            let boxes: Vec<[f64; 4]> = l.pads.iter().map(|p| p.outline.bbox()).collect();
            for b in &boxes {
                assert!(
                    b[0] >= EDGE_CLEARANCE_MM && b[1] >= EDGE_CLEARANCE_MM,
                    "{b:?}"
                );
                assert!(b[2] <= l.length_mm - EDGE_CLEARANCE_MM, "{b:?}");
                assert!(b[3] <= l.width_mm - EDGE_CLEARANCE_MM, "{b:?}");
            }
            let mut occ = Occupancy::new(l.length_mm, l.width_mm);
            for (i, b) in boxes.iter().enumerate() {
                // At least 0.1 mm of stencil between any two openings.
                let grown = [b[0] - 0.05, b[1] - 0.05, b[2] + 0.05, b[3] + 0.05];
                assert!(occ.hit(&grown).is_none(), "{board:?}: pad {i} overlaps");
                occ.add(grown);
            }
            // Fiducials: clear of every opening by at least 1 mm.
            for f in &l.fiducials {
                for b in &boxes {
                    let dx = (b[0] - f[0]).max(f[0] - b[2]).max(0.0);
                    let dy = (b[1] - f[1]).max(f[1] - b[3]).max(0.0);
                    assert!(dx.hypot(dy) >= 1.0, "{f:?} {b:?}");
                }
            }
        }
    }

    #[test]
    fn shipped_files_are_the_generated_layouts_byte_for_byte() {
        for board in LayoutBoard::ALL {
            let l = generate(board);
            let bytes = l.gerber().unwrap();
            let again = generate(board).gerber().unwrap();
            assert_eq!(bytes, again, "{board:?}: not deterministic");
            let shipped = std::fs::read(scenes().join(board.shipped_file())).unwrap();
            assert!(
                shipped == bytes,
                "{board:?}: scenes/{} differs from the generator; regenerate with `dpsa layout --board {} --out scenes/{}`",
                board.shipped_file(),
                board.name(),
                board.shipped_file()
            );
            let text = String::from_utf8(bytes).unwrap();
            for want in [
                "%FSLAX46Y46*%",
                "%MOMM*%",
                "%TF.GenerationSoftware,dpsa,dpsa-layout,1*%",
                "%TF.FileFunction,Paste,Top*%",
                "%AMRoundRect*",
                "%TO.C,",
                "%TO.P,",
                "D03*",
                "M02*",
            ] {
                assert!(text.contains(want), "{board:?}: no {want}");
            }
            assert_eq!(text.matches("D03*").count(), l.pads.len());
            for kind in ["C,", "R,", "O,", "RoundRect,"] {
                assert!(
                    text.contains(&format!("%ADD1{kind}")) || text.contains(kind),
                    "{kind}"
                );
            }
        }
    }
}
