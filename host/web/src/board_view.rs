//! A board at a glance: every opening of its program drawn where the design puts it (board
//! `x` to the right, `y` up, as a Gerber viewer shows it), coloured by the pad's result on
//! this board, each call linked to its pad's page and labelled with its name and class; a
//! legend and a scale bar in mm. Inline SVG, presentation attributes only.
//!
//! The openings that passed are the same on every board of a program: drawn once per design
//! ([`Designs`] keeps the text) and repeated; only the calls are drawn per board.

use crate::crop::outline_svg;
use crate::html::esc;
use dpsa_line::config::Design;
use dpsa_line::store::PadRow;
use std::fmt::Write;
use std::path::Path;
use std::sync::{Arc, OnceLock};

/// The drawing's width, px.
pub const WIDTH_PX: f64 = 1000.0;

/// Most calls labelled on one board (the rest are drawn and linked, not labelled).
pub const MAX_LABELS: usize = 60;

/// The colours of a pad's result.
pub const PASS: &str = "#b9c2cc";
/// A warning's.
pub const WARN: &str = "#d4a017";
/// A failure's.
pub const FAIL: &str = "#d1242f";

/// A program's drawing frame: design mm to px.
#[derive(Clone, Copy, Debug)]
struct Frame {
    x0: f64,
    y1: f64,
    scale: f64,
    margin: f64,
    height: f64,
}

impl Frame {
    fn of(design: &Design) -> Frame {
        let b = design.pads.iter().map(|p| p.outline.bbox()).fold(
            [
                f64::INFINITY,
                f64::INFINITY,
                f64::NEG_INFINITY,
                f64::NEG_INFINITY,
            ],
            |a, b| {
                [
                    a[0].min(b[0]),
                    a[1].min(b[1]),
                    a[2].max(b[2]),
                    a[3].max(b[3]),
                ]
            },
        );
        let (w, h) = ((b[2] - b[0]).max(1.0), (b[3] - b[1]).max(1.0));
        let margin = 40.0;
        let scale = (WIDTH_PX - 2.0 * margin) / w;
        Frame {
            x0: b[0],
            y1: b[3],
            scale,
            margin,
            height: h * scale + 2.0 * margin + 30.0,
        }
    }

    fn at(&self, x: f64, y: f64) -> (f64, f64) {
        (
            self.margin + (x - self.x0) * self.scale,
            self.margin + (self.y1 - y) * self.scale,
        )
    }
}

/// The programs whose boards the pages can draw, each with its passing layer drawn once.
#[derive(Default)]
pub struct Designs {
    list: Vec<(Design, OnceLock<String>)>,
}

impl std::fmt::Debug for Designs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list()
            .entries(self.list.iter().map(|(d, _)| &d.program_hash))
            .finish()
    }
}

impl Designs {
    /// The programs at `paths` (an error names the file that could not be read).
    pub fn load(paths: &[&Path]) -> Result<Designs, dpsa_line::LineError> {
        let list = paths
            .iter()
            .map(|p| Ok((Design::load(p)?, OnceLock::new())))
            .collect::<Result<_, dpsa_line::LineError>>()?;
        Ok(Designs { list })
    }

    /// The programs given, as designs.
    pub fn from(designs: Vec<Design>) -> Designs {
        Designs {
            list: designs.into_iter().map(|d| (d, OnceLock::new())).collect(),
        }
    }

    /// How many.
    pub fn len(&self) -> usize {
        self.list.len()
    }

    /// None given.
    pub fn is_empty(&self) -> bool {
        self.list.is_empty()
    }

    /// The design of the program whose hash a board carries.
    fn find(&self, program_hash: &str) -> Option<&(Design, OnceLock<String>)> {
        self.list
            .iter()
            .find(|(d, _)| d.program_hash == program_hash)
    }

    /// The file of the program of hash `program_hash`, if given.
    pub fn path(&self, program_hash: &str) -> Option<&Path> {
        self.find(program_hash).map(|(d, _)| d.path.as_path())
    }

    /// Pad `k`'s package family under the program of hash `program_hash`.
    pub fn family(&self, program_hash: &str, k: u32) -> Option<&str> {
        let (d, _) = self.find(program_hash)?;
        d.families.get(k as usize)?.as_deref()
    }

    /// Pad `k`'s tolerance windows under the program of hash `program_hash` (its overrides
    /// applied), if that program was given.
    pub fn windows(&self, program_hash: &str, k: u32) -> Option<dpsa_inspect::program::Windows> {
        let (d, _) = self.find(program_hash)?;
        Some(d.program.windows_for(d.pads.get(k as usize)?))
    }
}

/// The calls among `pads` under the program of hash `program_hash`, failures last: each
/// pad row with its opening's centroid in design mm; `None` when that program was not given.
pub fn call_centres<'a>(
    designs: &Designs,
    program_hash: &str,
    pads: &'a [PadRow],
) -> Option<Vec<(&'a PadRow, [f64; 2])>> {
    let (design, _) = designs.find(program_hash)?;
    let mut calls: Vec<(&PadRow, [f64; 2])> = pads
        .iter()
        .filter(|p| p.level != "pass")
        .filter_map(|p| Some((p, design.pads.get(p.pad as usize)?.outline.centroid())))
        .collect();
    calls.sort_by_key(|(p, _)| (p.level == "fail", p.pad));
    Some(calls)
}

/// The board `id` of program `program_hash` with its pad rows: the drawing, or `None` when
/// no program of that hash was given.
pub fn board_svg(
    designs: &Arc<Designs>,
    program_hash: &str,
    id: i64,
    pads: &[PadRow],
) -> Option<String> {
    let (design, passing) = designs.find(program_hash)?;
    let f = Frame::of(design);
    let mut o = String::new();
    let _ = write!(
        o,
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w:.0}\" height=\"{h:.0}\" \
         viewBox=\"0 0 {w:.0} {h:.0}\" role=\"img\" aria-label=\"the board's pads by result\">\
         <rect x=\"0\" y=\"0\" width=\"{w:.0}\" height=\"{h:.0}\" fill=\"#1f2a36\"/>",
        w = WIDTH_PX,
        h = f.height
    );
    // Every opening in the pass colour, drawn once per program.
    o.push_str(passing.get_or_init(|| {
        let mut g = format!("<g fill=\"{PASS}\">");
        for p in &design.pads {
            g.push_str(&outline_svg(&p.outline, |x, y| f.at(x, y), f.scale, ""));
        }
        g.push_str("</g>");
        g
    }));
    // The calls over them, failures last (on top), each linked.
    let mut calls: Vec<&PadRow> = pads
        .iter()
        .filter(|p| p.level != "pass" && (p.pad as usize) < design.pads.len())
        .collect();
    calls.sort_by_key(|p| (p.level == "fail", p.pad));
    for p in &calls {
        let pad = &design.pads[p.pad as usize];
        let colour = if p.level == "fail" { FAIL } else { WARN };
        let what = format!(
            "{} {}{}",
            p.name,
            p.level,
            p.class
                .as_deref()
                .map(|c| format!(": {c}"))
                .unwrap_or_default()
        );
        let _ = write!(
            o,
            "<a href=\"/board/{id}/pad/{k}\"><title>{t}</title>{shape}</a>",
            k = p.pad,
            t = esc(&what),
            shape = outline_svg(
                &pad.outline,
                |x, y| f.at(x, y),
                f.scale,
                &format!("fill=\"{colour}\" stroke=\"#ffffff\" stroke-width=\"1\""),
            )
        );
    }
    // Labels: each call marked by a ring (a pad is a few px on a big board) and named where
    // its name overlaps no other (failures placed first).
    let mut placed = dpsa_formats::labels::Placed::default();
    let bounds = [2.0, 2.0, WIDTH_PX - 2.0, f.height - 24.0];
    for p in calls.iter().rev().take(MAX_LABELS) {
        let pad = &design.pads[p.pad as usize];
        let c = pad.outline.centroid();
        let (x, y) = f.at(c[0], c[1]);
        let colour = if p.level == "fail" { FAIL } else { WARN };
        let label = format!(
            "{} {}",
            p.name,
            p.class.as_deref().unwrap_or(p.level.as_str())
        );
        let (tx, ty) = placed.place(x, y, 7.0 * label.chars().count() as f64, 14.0, bounds);
        let _ = write!(
            o,
            "<a href=\"/board/{id}/pad/{k}\"><circle cx=\"{x:.1}\" cy=\"{y:.1}\" r=\"9\" \
             fill=\"none\" stroke=\"{colour}\" stroke-width=\"2\"/><line x1=\"{x:.1}\" \
             y1=\"{y:.1}\" x2=\"{lx:.1}\" y2=\"{ly:.1}\" stroke=\"{colour}\" \
             stroke-width=\"1\"/><text x=\"{tx:.1}\" y=\"{ty:.1}\" font-size=\"12\" \
             fill=\"#ffffff\" stroke=\"#1f2a36\" stroke-width=\"3\" \
             paint-order=\"stroke\">{l}</text></a>",
            k = p.pad,
            lx = tx.clamp(x - 200.0, x + 200.0),
            ly = ty - 4.0,
            l = esc(&label)
        );
    }
    if calls.len() > MAX_LABELS {
        let _ = write!(
            o,
            "<text x=\"{:.0}\" y=\"{:.0}\" font-size=\"12\" fill=\"#ffffff\">{} more calls \
             not labelled: see the list</text>",
            f.margin,
            f.margin - 14.0,
            calls.len() - MAX_LABELS
        );
    }
    // Legend and scale bar.
    let y = f.height - 16.0;
    let mut x = f.margin;
    for (name, colour) in [("pass", PASS), ("warn", WARN), ("fail", FAIL)] {
        let _ = write!(
            o,
            "<rect x=\"{x:.0}\" y=\"{:.0}\" width=\"14\" height=\"10\" fill=\"{colour}\"/>\
             <text x=\"{:.0}\" y=\"{y:.0}\" font-size=\"12\" fill=\"#ffffff\">{name}</text>",
            y - 9.0,
            x + 18.0
        );
        x += 70.0;
    }
    let mm = dpsa_formats::labels::scale_bar_mm(200.0 / f.scale);
    let len = mm * f.scale;
    let bx = WIDTH_PX - f.margin - len;
    let _ = write!(
        o,
        "<line x1=\"{bx:.1}\" x2=\"{:.1}\" y1=\"{:.0}\" y2=\"{:.0}\" stroke=\"#ffffff\" \
         stroke-width=\"3\"/><text x=\"{:.1}\" y=\"{:.0}\" font-size=\"12\" fill=\"#ffffff\" \
         text-anchor=\"middle\">{mm} mm</text><text x=\"{:.0}\" y=\"{y:.0}\" font-size=\"12\" \
         fill=\"#ffffff\">design x to the right, y up</text></svg>",
        bx + len,
        y - 4.0,
        y - 4.0,
        bx + len / 2.0,
        y - 10.0,
        f.margin + 230.0
    );
    Some(o)
}
