//! The files of `dpsa inspect --out DIR`:
//!
//! | file | what |
//! | --- | --- |
//! | `pads.csv` | one row per pad; the IPC-CFX `SolderPasteMeasurement` names where they exist (`ComponentPad`, `PasteVolume`, `PasteHeight`, `PasteXOffset`, `PasteYOffset`, `Result`), then ours |
//! | `report.json` | what `--json` prints |
//! | `cfx_units_inspected.json` | an IPC-CFX 1.x `UnitsInspected` message (JSON envelope, `InspectionMethod` SPI), one `SolderPasteMeasurement` per pad, the failures as `DefectsFound` |
//! | `overview.png` | the board's heights above its local surface in grey (the bow taken out: `dpsa_formats::surface`), board x to the right and y up, every opening outlined in its verdict's colour (green pass, amber warning, red failure, magenta not measurable), every call ringed and labelled `REF.PIN class` where no label covers another, the fiducials marked, a title, a legend and a scale bar in mm |
//! | `gallery/NNN_class_pad.png` | every failure (at most [`MAX_GALLERY`]): its name, class and measures against their fail limits; the heights above the pad's local surface around it (false colour 0 to 1.6 x stencil with a colour bar in um, board x right and y up with axes in mm, the opening dashed in white, the cut in black, no height in dark grey) over the profile along the cut (um against mm, the stencil thickness dashed) |

use crate::error::InspectError;
use crate::map::BoardMap;
use crate::measure::PadMeasurement;
use crate::program::Program;
use crate::run::Inspection;
use crate::verdict::{Call, Level};
use dpsa_formats::files::FileError;
use dpsa_gerber::pads::{Pad, Rigid};
use image::{ImageBuffer, Rgb, RgbImage};
use serde_json::{json, Value};
use std::fmt::Write as _;
use std::path::Path;

/// Most defect pictures written.
pub const MAX_GALLERY: usize = 100;

fn result_name(c: &Call) -> &'static str {
    match c.level {
        Level::Pass | Level::Warn => "Passed",
        Level::Fail => "Failed",
    }
}

/// A pad's name as the reports give it: `component.pin` when the placement names it, else the
/// layer's pad name.
pub fn cfx_pad(p: &Pad) -> String {
    match (&p.component, &p.pin) {
        (Some(c), Some(n)) => format!("{c}.{n}"),
        _ => p.name(),
    }
}

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

fn num(v: f64, digits: usize) -> String {
    if v.is_finite() {
        format!("{v:.digits$}")
    } else {
        String::new()
    }
}

/// `pads.csv`: a header and one row per pad, in the layer's order (an empty field where a
/// figure is NaN).
pub fn csv(pads: &[Pad], i: &Inspection) -> String {
    let mut s = String::from(
        "ComponentPad,Component,Pin,PadClass,X_mm,Y_mm,Result,Level,Class,PasteVolume_um3,VolumePct,VolumeU_pct,PasteHeight_um,HeightU_um,HeightPct,HeightMax_um,Area_mm2,AreaPct,PasteXOffset_um,PasteYOffset_um,OffsetPct,ShapePct,Coverage,BridgedTo,Findings\n",
    );
    for ((p, m), c) in pads.iter().zip(&i.measurements).zip(&i.calls) {
        let cen = p.outline.centroid();
        let bridged: Vec<String> = m.bridged_to.iter().map(|&j| cfx_pad(&pads[j])).collect();
        let findings: Vec<String> = c
            .findings
            .iter()
            .map(|(l, k)| format!("{}:{}", l.name(), k.name()))
            .collect();
        let _ = writeln!(
            s,
            "{},{},{},{},{:.4},{:.4},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{:.4},{},{}",
            csv_field(&cfx_pad(p)),
            csv_field(p.component.as_deref().unwrap_or("")),
            csv_field(p.pin.as_deref().unwrap_or("")),
            csv_field(p.aperture.as_deref().unwrap_or("")),
            cen[0],
            cen[1],
            result_name(c),
            c.level.name(),
            c.class.map(|k| k.name()).unwrap_or(""),
            num(m.volume_um3, 0),
            num(m.volume_pct, 2),
            num(m.volume_u_pct, 2),
            num(m.height_um, 2),
            num(m.height_u_um, 2),
            num(m.height_pct, 2),
            num(m.height_max_um, 2),
            num(m.area_mm2, 5),
            num(m.area_pct, 2),
            num(m.offset_um[0], 1),
            num(m.offset_um[1], 1),
            num(m.offset_pct, 2),
            num(m.shape_pct, 2),
            m.coverage,
            csv_field(&bridged.join(" ")),
            csv_field(&findings.join(" ")),
        );
    }
    s
}

/// A random-looking, reproducible UUID (version 4 layout) from a seed.
fn uuid(seed: u64, n: u64) -> String {
    let mut x = seed ^ n.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    let mut next = || {
        x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = x;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    let (a, b) = (next(), next());
    format!(
        "{:08x}-{:04x}-4{:03x}-{:04x}-{:012x}",
        a >> 32,
        (a >> 16) & 0xffff,
        a & 0xfff,
        0x8000 | (b >> 48) & 0x3fff,
        b & 0xffff_ffff_ffff
    )
}

/// UTC time as ISO 8601 (civil date from days since 1970).
pub fn iso_now() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    let [y, m, d, h, mi, s] = dpsa_formats::time::utc(i64::try_from(secs).unwrap_or(0));
    format!("{y:04}-{m:02}-{d:02}T{h:02}:{mi:02}:{s:02}Z")
}

/// `v` rounded to `decimals` decimal places (a negative count rounds to tens, hundreds...).
fn round_to(v: f64, decimals: i32) -> f64 {
    let k = 10f64.powi(decimals);
    let r = (v * k).round() / k;
    // Printing `r` may still show a binary tail (0.1 * 3); parsing its rounded decimal text
    // gives the closest f64 to the decimal, which prints short.
    format!("{r:.*}", decimals.max(0) as usize)
        .parse()
        .unwrap_or(r)
}

/// Decimal places that carry meaning, per unit: volumes to 1 um^3, heights to 0.01 um (the
/// map's heights are f32 um, its PNG LSB 0.25 um) and lateral offsets to 0.01 um.
fn decimals(units: &str) -> i32 {
    match units {
        "um3" => 0,
        "um" => 2,
        _ => 3,
    }
}

fn numeric(value: f64, units: &str, expected: f64, lo: f64, hi: f64) -> Value {
    let d = decimals(units);
    let f = |v: f64| {
        if v.is_finite() {
            json!(round_to(v, d))
        } else {
            Value::Null
        }
    };
    json!({
        "Value": f(value),
        "ValueUnits": units,
        "ExpectedValue": f(expected),
        "ExpectedValueUnits": units,
        "MinimumAcceptableValue": f(lo),
        "MaximumAcceptableValue": f(hi),
    })
}

/// The IPC-CFX `UnitsInspected` message of one board: `unit` is its identifier, `recipe` the
/// program's name.
pub fn cfx(pads: &[Pad], i: &Inspection, program: &Program, unit: &str, recipe: &str) -> Value {
    let seed = dpsa_core::frames::fnv1a64(unit.as_bytes());
    let mut measurements = Vec::with_capacity(pads.len());
    let mut defects = Vec::new();
    for (k, ((p, m), c)) in pads.iter().zip(&i.measurements).zip(&i.calls).enumerate() {
        let w = program.windows_for(p);
        let ov = m.opening_mm2 * program.stencil_um * 1e6;
        let st = program.stencil_um;
        let b = p.outline.bbox();
        let (sx, sy) = ((b[2] - b[0]) * 1000.0, (b[3] - b[1]) * 1000.0);
        measurements.push(json!({
            "$type": "CFX.Structures.SolderPasteInspection.SolderPasteMeasurement, CFX",
            "UniqueIdentifier": uuid(seed, 2 * k as u64 + 1),
            "MeasurementName": cfx_pad(p),
            "Result": result_name(c),
            "ComponentPad": cfx_pad(p),
            "PasteVolume": numeric(m.volume_um3, "um3", ov, ov * w.volume_pct.fail[0] / 100.0, ov * w.volume_pct.fail[1] / 100.0),
            "PasteHeight": numeric(m.height_um, "um", st, st * w.height_pct.fail[0] / 100.0, st * w.height_pct.fail[1] / 100.0),
            "PasteXOffset": numeric(m.offset_um[0], "um", 0.0, -sx * w.offset_pct.fail / 100.0, sx * w.offset_pct.fail / 100.0),
            "PasteYOffset": numeric(m.offset_um[1], "um", 0.0, -sy * w.offset_pct.fail / 100.0, sy * w.offset_pct.fail / 100.0),
        }));
        if c.level == Level::Fail {
            let class = c.class.map(|k| k.name()).unwrap_or("?");
            defects.push(json!({
                "UniqueIdentifier": uuid(seed, 2 * k as u64 + 2),
                "DefectCode": class.to_uppercase(),
                "DefectCategory": "SolderPaste",
                "Description": format!("{} {}", cfx_pad(p), class.replace('_', " ")),
                "ComponentOfInterest": {
                    "ReferenceDesignator": p.component.clone().unwrap_or_else(|| p.name()),
                },
                "RelatedMeasurements": [cfx_pad(p)],
            }));
        }
    }
    let failed = i.calls.iter().any(|c| c.level == Level::Fail);
    let result = if failed { "Failed" } else { "Passed" };
    json!({
        "MessageName": "CFX.Production.TestAndInspection.UnitsInspected",
        "Version": "1.7",
        "TimeStamp": iso_now(),
        "UniqueID": uuid(seed, 0),
        "Source": "dpsa",
        "Target": Value::Null,
        "RequestID": Value::Null,
        "MessageBody": {
            "$type": "CFX.Production.TestAndInspection.UnitsInspected, CFX",
            "TransactionId": uuid(seed, u64::MAX),
            "InspectionMethod": "SPI",
            "SampleType": "Production",
            // The inspecting tool and its version (no human operator).
            "Inspector": {
                "OperatorIdentifier": concat!("dpsa ", env!("CARGO_PKG_VERSION")),
                "ActorType": "Robot",
                "LoginName": "dpsa",
            },
            "RecipeName": recipe,
            "InspectedUnits": [{
                "UnitIdentifier": unit,
                "UnitPositionNumber": 1,
                "OverallResult": result,
                "Inspections": [{
                    "UniqueIdentifier": uuid(seed, u64::MAX - 1),
                    "InspectionName": "INSPECT_PASTE_DEPOSITS",
                    "Result": result,
                    "DefectsFound": defects,
                    "Measurements": measurements,
                }],
            }],
        },
    })
}

fn level_colour(c: &Call, m: &PadMeasurement) -> [u8; 3] {
    if m.unmeasurable.is_some() {
        return [230, 0, 230];
    }
    match c.level {
        Level::Pass => [0, 200, 60],
        Level::Warn => [255, 170, 0],
        Level::Fail => [255, 30, 30],
    }
}

/// What [`overview`] marks: an opening on the board, its colour, and the label of a call.
#[derive(Clone, Debug)]
pub struct Mark {
    /// The opening on the board, mm.
    pub outline: dpsa_gerber::pads::Outline,
    /// Its verdict's colour.
    pub colour: [u8; 3],
    /// For a call: its label (`REF.PIN class`), and whether it failed.
    pub call: Option<(String, bool)>,
}

/// Where the overview puts the board: `f` map pixels a pixel, board `x` to the right and `y`
/// up (a Gerber viewer's view), inside margins for the title, legend and scale.
#[derive(Clone, Copy, Debug)]
pub struct OverviewFrame {
    /// Map pixels per image pixel.
    pub f: usize,
    /// The map's picture, px: along `x` and along `y`.
    pub size: (usize, usize),
    /// Left and top margins, px.
    pub origin: (usize, usize),
    /// The whole image, px.
    pub image: (u32, u32),
}

impl OverviewFrame {
    /// The frame of `grid` at most `max_px` map pixels on its longer side.
    pub fn of(grid: &dpsa_formats::grid::BoardGrid, max_px: usize) -> OverviewFrame {
        let f = grid.rows.max(grid.width).div_ceil(max_px.max(1)).max(1);
        let size = (grid.rows.div_ceil(f), grid.width.div_ceil(f));
        let origin = (12, 40);
        OverviewFrame {
            f,
            size,
            origin,
            image: ((size.0 + 24) as u32, (size.1 + origin.1 + 56) as u32),
        }
    }

    /// The image pixel of board point `(x, y)` mm on `grid`, fractional.
    pub fn pixel(&self, grid: &dpsa_formats::grid::BoardGrid, x: f64, y: f64) -> (f64, f64) {
        let step = grid.pitch_mm * self.f as f64;
        (
            self.origin.0 as f64 + (x - grid.x0_mm) / step,
            self.origin.1 as f64 + self.size.1 as f64 - (y - grid.y0_mm) / step,
        )
    }
}

/// `overview.png`: the board's heights in grey with every opening outlined in its verdict's
/// colour, board `x` to the right and `y` up, at most `max_px` map pixels on the longer side;
/// every call ringed and labelled (`REF.PIN class`, placed where no label covers another),
/// the fiducials marked, a title, a legend and a scale bar in mm.
pub fn overview(
    map: &BoardMap,
    pads: &[Pad],
    t: &Rigid,
    i: &Inspection,
    program: &Program,
    max_px: usize,
) -> RgbImage {
    let marks: Vec<Mark> = pads
        .iter()
        .zip(&i.measurements)
        .zip(&i.calls)
        .map(|((p, m), c)| Mark {
            outline: p.outline.transformed(t),
            colour: level_colour(c, m),
            call: (c.level != Level::Pass).then(|| {
                let class = c.class.map_or(c.level.name(), |k| k.name());
                (format!("{} {class}", cfx_pad(p)), c.level == Level::Fail)
            }),
        })
        .collect();
    let fiducials: Vec<[f64; 2]> = program
        .fiducials
        .points_mm
        .iter()
        .map(|&q| t.apply(q))
        .collect();
    let count = |l: Level| i.calls.iter().filter(|c| c.level == l).count();
    let title = format!(
        "{}{} pads: {} pass, {} warn, {} fail",
        map.board_id
            .map(|b| format!("board {b}: "))
            .unwrap_or_default(),
        pads.len(),
        count(Level::Pass),
        count(Level::Warn),
        count(Level::Fail)
    );
    draw_overview(map, &marks, &fiducials, &title, max_px)
}

/// Most calls labelled on the overview (the rest ringed).
pub const OVERVIEW_LABELS: usize = 80;

/// The overview of `map` with `marks`, `fiducials` (board mm) and `title` (see [`overview`]).
pub fn draw_overview(
    map: &BoardMap,
    marks: &[Mark],
    fiducials: &[[f64; 2]],
    title: &str,
    max_px: usize,
) -> RgbImage {
    let g = &map.grid;
    let fr = OverviewFrame::of(g, max_px);
    let (f, (nu, nv), (ou, ov)) = (fr.f, fr.size, fr.origin);
    // The heights drawn (every f-th map pixel), above the board's local surface: the bow
    // taken out, the paste bright on a dark board.
    let mut shown = dpsa_formats::grid::Grid::invalid(nv, nu);
    for u in 0..nu {
        for (k, out) in shown.data[u * nv..(u + 1) * nv].iter_mut().enumerate() {
            *out = map
                .heights
                .at(u * f, (k * f).min(g.width.saturating_sub(1)));
        }
    }
    let cell = (dpsa_formats::surface::SURFACE_CELL_MM / (g.pitch_mm * f as f64)).round();
    let surface = dpsa_formats::surface::local_surface(&shown, (cell as usize).max(2));
    for (h, s) in shown.data.iter_mut().zip(&surface.data) {
        *h -= s;
    }
    // White from the 99th percentile up (the paste's tops on a printed board), at least 20 um
    // (a board with hardly any paste keeps its bare board dark).
    let top = dpsa_formats::board_map::colour_range(&shown).map_or(20.0, |r| r.1.max(20.0));
    let mut img: RgbImage = ImageBuffer::from_pixel(fr.image.0, fr.image.1, Rgb([24, 28, 36]));
    // Image column u is map row u f (board x), image row v is map column (nv - 1 - v) f
    // (board y up).
    for v in 0..nv {
        let k = nv - 1 - v;
        for u in 0..nu {
            let px = shown.data[u * nv + k];
            let q = if px.is_finite() {
                ((px / top).clamp(0.0, 1.0) * 200.0 + 30.0) as u8
            } else {
                12
            };
            img.put_pixel((ou + u) as u32, (ov + v) as u32, Rgb([q, q, q]));
        }
    }
    let step = g.pitch_mm * f as f64;
    // Every opening outlined in its colour (failures thicker).
    for m in marks {
        let b = m.outline.bbox();
        let width = if matches!(m.call, Some((_, true))) {
            1.6
        } else {
            0.6
        };
        let (u0, v1) = fr.pixel(g, b[0] - step, b[1] - step);
        let (u1, v0) = fr.pixel(g, b[2] + step, b[3] + step);
        for v in (v0.floor().max(ov as f64) as usize)..(v1.ceil() as usize).min(ov + nv) {
            for u in (u0.floor().max(ou as f64) as usize)..(u1.ceil() as usize).min(ou + nu) {
                let x = g.x0_mm + ((u - ou) as f64 + 0.5) * step;
                let y = g.y0_mm + ((ov + nv - v) as f64 - 0.5) * step;
                if m.outline.signed_distance([x, y]).abs() <= width * step {
                    img.put_pixel(u as u32, v as u32, Rgb(m.colour));
                }
            }
        }
    }
    let white = [255, 255, 255];
    let dark = [24, 28, 36];
    let (w, h) = (f64::from(fr.image.0), f64::from(fr.image.1));
    dpsa_formats::picture::draw(&mut img, |root| {
        use plotters::prelude::*;
        // Fiducials: a cyan ring and cross.
        let cyan = dpsa_formats::picture::rgb([0, 210, 230]);
        for q in fiducials {
            let (x, y) = fr.pixel(g, q[0], q[1]);
            let (x, y) = (x as i32, y as i32);
            root.draw(&Circle::new((x, y), 10, cyan.stroke_width(2)))?;
            root.draw(&PathElement::new(
                vec![(x - 14, y), (x + 14, y)],
                cyan.stroke_width(1),
            ))?;
            root.draw(&PathElement::new(
                vec![(x, y - 14), (x, y + 14)],
                cyan.stroke_width(1),
            ))?;
        }
        // The calls: failures first, ringed and labelled where no label covers another.
        let mut calls: Vec<&Mark> = marks.iter().filter(|m| m.call.is_some()).collect();
        calls.sort_by_key(|m| !matches!(m.call, Some((_, true))));
        let mut placed = dpsa_formats::labels::Placed::default();
        let bounds = [2.0, ov as f64, w - 2.0, (ov + nv) as f64];
        let size = 13.0;
        for (k, m) in calls.iter().enumerate() {
            let c = m.outline.centroid();
            let (x, y) = fr.pixel(g, c[0], c[1]);
            let colour = dpsa_formats::picture::rgb(m.colour);
            root.draw(&Circle::new(
                (x as i32, y as i32),
                9,
                colour.stroke_width(2),
            ))?;
            if k >= OVERVIEW_LABELS {
                continue;
            }
            let label = m.call.as_ref().map_or("", |c| c.0.as_str());
            let lw = dpsa_formats::picture::text_width(label, size) + 4.0;
            let (tx, ty) = placed.place(x, y, lw, size + 3.0, bounds);
            let (lx, ly) = (tx.clamp(x - 300.0, x + 300.0), ty - size / 2.0);
            root.draw(&PathElement::new(
                vec![(x as i32, y as i32), (lx as i32, ly as i32)],
                colour.stroke_width(1),
            ))?;
            dpsa_formats::picture::text(root, (tx as i32, ty as i32), size, white, dark, label)?;
        }
        if calls.len() > OVERVIEW_LABELS {
            dpsa_formats::picture::text(
                root,
                (ou as i32, (ov - 4) as i32),
                12.0,
                white,
                dark,
                &format!(
                    "{} more calls ringed, not labelled: see pads.csv",
                    calls.len() - OVERVIEW_LABELS
                ),
            )?;
        }
        // Title, legend, scale bar.
        dpsa_formats::picture::text(root, (ou as i32, 24), 16.0, white, dark, title)?;
        let y = (h - 18.0) as i32;
        let mut x = ou as i32;
        for (name, c) in [
            ("pass", [0, 200, 60]),
            ("warn", [255, 170, 0]),
            ("fail", [255, 30, 30]),
            ("not measurable", [230, 0, 230]),
            ("fiducial", [0, 210, 230]),
        ] {
            root.draw(&Rectangle::new(
                [(x, y - 11), (x + 14, y - 1)],
                dpsa_formats::picture::rgb(c).filled(),
            ))?;
            dpsa_formats::picture::text(root, (x + 19, y), 13.0, white, dark, name)?;
            x += 19 + dpsa_formats::picture::text_width(name, 13.0) as i32 + 18;
        }
        dpsa_formats::picture::text(
            root,
            (x + 10, y),
            13.0,
            [200, 200, 200],
            dark,
            "x right, y up; grey: height above the board",
        )?;
        let mm = dpsa_formats::labels::scale_bar_mm(0.2 * nu as f64 * step);
        let len = (mm / step).round() as i32;
        let x1 = (w as i32) - 14;
        root.draw(&PathElement::new(
            vec![(x1 - len, y - 4), (x1, y - 4)],
            WHITE.stroke_width(3),
        ))?;
        let label = format!("{mm} mm");
        let lw = dpsa_formats::picture::text_width(&label, 13.0) as i32;
        dpsa_formats::picture::text(
            root,
            (x1 - len / 2 - lw / 2, y - 9),
            13.0,
            white,
            dark,
            &label,
        )?;
        Ok(())
    });
    img
}

/// One defect picture (`gallery/`): a title (the pad, its class, its measures against their
/// fail limits), the heights above the pad's local surface around it (false colour 0 to 1.6 x
/// the stencil with a colour bar in um, board x to the right and y up, axes in mm, the opening
/// dashed in white, the profile's cut in black, no height in dark grey) over the profile along
/// the cut (um against mm, the stencil's thickness dashed).
pub(crate) fn defect_picture(
    map: &BoardMap,
    p: &Pad,
    m: &PadMeasurement,
    c: &Call,
    t: &Rigid,
    program: &Program,
) -> RgbImage {
    let stencil = program.stencil_um;
    let Some(crop) = crate::crop::pad_crop(map, p, m, t) else {
        // No surface fitted (nothing measurable there): the title alone says so.
        let mut img: RgbImage = ImageBuffer::from_pixel(520, 60, Rgb([255, 255, 255]));
        let title = format!(
            "{} · {} · no surface to measure against",
            cfx_pad(p),
            call_name(c)
        );
        dpsa_formats::picture::draw(&mut img, |root| {
            dpsa_formats::picture::text(root, (8, 26), 15.0, [0, 0, 0], [255, 255, 255], &title)
        });
        return img;
    };
    let (nx, ny) = (crop.nx, crop.ny);
    let s = (300 / nx.max(ny)).clamp(1, 12);
    let (left, top, bar) = (52usize, 56usize, 70usize);
    let (cw, ch) = (nx * s, ny * s);
    let prof_top = top + ch + 44;
    let prof_h = 140usize;
    let width = (left + cw + 20 + bar).max(560);
    let height = prof_top + prof_h + 40;
    let mut img: RgbImage =
        ImageBuffer::from_pixel(width as u32, height as u32, Rgb([255, 255, 255]));
    let top_um = 1.6 * stencil;
    let colour = |v: f32| {
        if v.is_finite() {
            dpsa_formats::images::colour((f64::from(v) / top_um).clamp(0.0, 1.0))
        } else {
            [60, 60, 60]
        }
    };
    let o = &crop.outline;
    let pitch = crop.pitch_mm;
    // The crop: sample (ix, iy) at image (left + ix s, top + (ny - 1 - iy) s).
    for ix in 0..nx {
        for iy in 0..ny {
            let col = colour(crop.at(ix, iy));
            let (x, y) = crop.centre(ix, iy);
            let edge = o.signed_distance([x, y]).abs() <= 0.5 * pitch;
            for a in 0..s {
                for b in 0..s {
                    let px = if edge && (ix + iy) % 2 == 0 {
                        [255, 255, 255]
                    } else {
                        col
                    };
                    img.put_pixel(
                        (left + ix * s + a) as u32,
                        (top + (ny - 1 - iy) * s + b) as u32,
                        Rgb(px),
                    );
                }
            }
        }
    }
    let cut = {
        let cy = o.centroid()[1];
        (((cy - crop.y0_mm) / pitch).round().max(0.0) as usize).min(ny - 1)
    };
    let windows = program.windows_for(p);
    let lim = |w: crate::program::Window| format!("{:.0}-{:.0}", w.fail[0], w.fail[1]);
    let title = format!("{} · {}", cfx_pad(p), call_name(c));
    let figures = format!(
        "volume {:.1} % ({}) · height {:.1} um, {:.1} % ({}) · area {:.1} % ({}) · offset {:.0}, {:.0} um",
        m.volume_pct,
        lim(windows.volume_pct),
        m.height_um,
        m.height_pct,
        lim(windows.height_pct),
        m.area_pct,
        lim(windows.area_pct),
        m.offset_um[0],
        m.offset_um[1]
    );
    let profile: Vec<(f64, f32)> = (0..nx)
        .map(|ix| (crop.centre(ix, cut).0, crop.at(ix, cut)))
        .collect();
    let (x_lo, x_hi) = (
        crop.x0_mm - pitch / 2.0,
        crop.x0_mm + (nx as f64 - 0.5) * pitch,
    );
    let (y_lo, y_hi) = (
        crop.y0_mm - pitch / 2.0,
        crop.y0_mm + (ny as f64 - 0.5) * pitch,
    );
    dpsa_formats::picture::draw(&mut img, |root| {
        use plotters::prelude::*;
        let (ink, paper) = ([20, 24, 30], [255, 255, 255]);
        let text =
            |root, at, size, s: &str| dpsa_formats::picture::text(root, at, size, ink, paper, s);
        text(root, (8, 20), 15.0, &title)?;
        text(root, (8, 40), 12.0, &figures)?;
        let grey = RGBColor(90, 96, 106);
        // The cut.
        let cy = (top + (ny - 1 - cut) * s + s / 2) as i32;
        root.draw(&PathElement::new(
            vec![(left as i32, cy), ((left + cw) as i32, cy)],
            BLACK.stroke_width(1),
        ))?;
        text(root, ((left + cw + 3) as i32, cy + 5), 11.0, "cut")?;
        // Axes of the crop, mm.
        let sx = |x: f64| left as f64 + (x - x_lo) / pitch * s as f64;
        let sy = |y: f64| top as f64 + (y_hi - y) / pitch * s as f64;
        root.draw(&Rectangle::new(
            [
                (left as i32, top as i32),
                ((left + cw) as i32, (top + ch) as i32),
            ],
            grey.stroke_width(1),
        ))?;
        for x in dpsa_formats::labels::ticks(x_lo, x_hi, 4) {
            let u = sx(x) as i32;
            root.draw(&PathElement::new(
                vec![(u, (top + ch) as i32), (u, (top + ch + 4) as i32)],
                grey.stroke_width(1),
            ))?;
            text(
                root,
                (u - 12, (top + ch + 17) as i32),
                11.0,
                &format!("{x:.1}"),
            )?;
        }
        for y in dpsa_formats::labels::ticks(y_lo, y_hi, 4) {
            let v = sy(y) as i32;
            root.draw(&PathElement::new(
                vec![(left as i32 - 4, v), (left as i32, v)],
                grey.stroke_width(1),
            ))?;
            text(root, (4, v + 4), 11.0, &format!("{y:.1}"))?;
        }
        text(
            root,
            ((left + cw / 2) as i32 - 40, (top + ch + 31) as i32),
            11.0,
            "board x, mm (y up)",
        )?;
        // The colour bar, um.
        let bx = (left + cw + 24) as i32;
        for k in 0..ch {
            let tv = 1.0 - (k as f64 + 0.5) / ch as f64;
            let c = dpsa_formats::images::colour(tv);
            root.draw(&PathElement::new(
                vec![(bx, (top + k) as i32), (bx + 12, (top + k) as i32)],
                dpsa_formats::picture::rgb(c).stroke_width(1),
            ))?;
        }
        for um in dpsa_formats::labels::ticks(0.0, top_um, 4) {
            let v = (top as f64 + (1.0 - um / top_um) * ch as f64) as i32;
            text(root, (bx + 16, v + 4), 11.0, &format!("{um:.0}"))?;
        }
        text(root, (bx, top as i32 - 6), 11.0, "um")?;
        // The profile along the cut.
        let (pl, pr) = (left as f64, (width - 14) as f64);
        let (pt, pb) = (prof_top as f64, (prof_top + prof_h) as f64);
        let valid: Vec<f64> = profile
            .iter()
            .filter(|q| q.1.is_finite())
            .map(|q| f64::from(q.1))
            .collect();
        let lo = valid.iter().fold(0.0f64, |a, &v| a.min(v)) - 5.0;
        let hi = valid.iter().fold(stencil, |a, &v| a.max(v)) * 1.1;
        let px = |x: f64| pl + (pr - pl) * (x - x_lo) / (x_hi - x_lo);
        let py = |v: f64| pb - (pb - pt) * (v - lo) / (hi - lo);
        root.draw(&Rectangle::new(
            [(pl as i32, pt as i32), (pr as i32, pb as i32)],
            grey.stroke_width(1),
        ))?;
        for v in dpsa_formats::labels::ticks(lo, hi, 4) {
            let y = py(v) as i32;
            root.draw(&PathElement::new(
                vec![(pl as i32 - 4, y), (pl as i32, y)],
                grey.stroke_width(1),
            ))?;
            text(root, (4, y + 4), 11.0, &format!("{v:.0}"))?;
        }
        for x in dpsa_formats::labels::ticks(x_lo, x_hi, 5) {
            let u = px(x) as i32;
            root.draw(&PathElement::new(
                vec![(u, pb as i32), (u, pb as i32 + 4)],
                grey.stroke_width(1),
            ))?;
            text(root, (u - 12, pb as i32 + 17), 11.0, &format!("{x:.1}"))?;
        }
        let ys = py(stencil) as i32;
        let mut x = pl as i32;
        while x < pr as i32 {
            root.draw(&PathElement::new(
                vec![(x, ys), ((x + 5).min(pr as i32), ys)],
                RGBColor(154, 103, 0).stroke_width(1),
            ))?;
            x += 9;
        }
        text(
            root,
            (pr as i32 - 96, ys - 3),
            11.0,
            &format!("stencil {stencil:.0} um"),
        )?;
        let mut run: Vec<(i32, i32)> = Vec::new();
        for &(x, v) in &profile {
            if v.is_finite() {
                run.push((px(x) as i32, py(f64::from(v)) as i32));
            } else if !run.is_empty() {
                root.draw(&PathElement::new(
                    std::mem::take(&mut run),
                    RGBColor(31, 111, 235).stroke_width(2),
                ))?;
            }
        }
        if !run.is_empty() {
            root.draw(&PathElement::new(
                run,
                RGBColor(31, 111, 235).stroke_width(2),
            ))?;
        }
        text(
            root,
            (pl as i32, pb as i32 + 31),
            11.0,
            "um above the local surface, along the cut; board x, mm",
        )?;
        Ok(())
    });
    img
}

/// A call as a person reads it: `fail insufficient`, `warn offset`.
fn call_name(c: &Call) -> String {
    match c.class {
        Some(k) => format!("{} {}", c.level.name(), k.name()),
        None => c.level.name().to_owned(),
    }
}

/// What the CFX message calls the board and the program.
#[derive(Clone, Copy, Debug)]
pub struct Names<'a> {
    /// The unit (board) identifier.
    pub unit: &'a str,
    /// The recipe (program) name.
    pub recipe: &'a str,
}

/// Kind of an inspection output directory (its [`dpsa_formats::files::MARKER`]).
pub const FORMAT: &str = "dpsa-inspection";

/// The files (and the `gallery` directory) [`write`](fn@write) puts into its directory.
pub const FILE_NAMES: [&str; 5] = [
    "pads.csv",
    "report.json",
    "cfx_units_inspected.json",
    "overview.png",
    "gallery",
];

/// Whether `dir` holds an earlier inspection output written before the marker existed: a
/// `report.json` and nothing but the files [`write`](fn@write) writes.
pub(crate) fn is_inspection_dir(dir: &Path) -> bool {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return false;
    };
    dir.join("report.json").is_file()
        && entries.flatten().all(|e| {
            let n = e.file_name();
            FILE_NAMES.iter().any(|f| n == *f)
        })
}

/// Refuses (before any work) a destination that an inspection output may not replace.
pub(crate) fn check_destination(dir: &Path) -> Result<(), FileError> {
    dpsa_formats::files::check_output_dir(dir, DIR_KIND)
}

/// An inspection output directory, for [`dpsa_formats::files::OutputDir`].
pub const DIR_KIND: dpsa_formats::files::DirKind = dpsa_formats::files::DirKind {
    format: FORMAT,
    noun: "inspection report",
    ours: is_inspection_dir,
};

/// Writes every file of the report into `dir`, whole or not at all: built in a hidden
/// directory beside it and swapped in at the end (an earlier report there is replaced with
/// all its gallery images, see [`dpsa_formats::files::OutputDir`]). `report_again` gives the final
/// `report.json` once the other files are written (with the time they took).
#[allow(clippy::too_many_arguments)]
pub fn write(
    dir: &Path,
    map: &BoardMap,
    pads: &[Pad],
    i: &Inspection,
    program: &Program,
    report: &Value,
    names: Names,
    report_again: impl FnOnce() -> Result<Value, InspectError>,
) -> Result<usize, InspectError> {
    let staging = dpsa_formats::files::OutputDir::create(dir, DIR_KIND)?;
    let path = staging.path();
    // The overview (the largest image) in a thread of its own beside the other files.
    let (overview, n) = std::thread::scope(|s| {
        let o = s.spawn(|| {
            let t = i.registration.transform;
            dpsa_formats::images::save_png(
                &overview(map, pads, &t, i, program, 2400),
                &path.join("overview.png"),
            )
        });
        let n = write_tables_and_gallery(path, map, pads, i, program, report, names);
        (o.join(), n)
    });
    // A panic there is a bug: carried on as this thread's own.
    overview.unwrap_or_else(|e| std::panic::resume_unwind(e))?;
    let n = n?;
    dpsa_formats::files::write_bytes(
        &path.join("report.json"),
        serde_json::to_string_pretty(&report_again()?)?.as_bytes(),
    )?;
    staging.commit()?;
    Ok(n)
}

/// `pads.csv`, `report.json`, the CFX message and the gallery of failures (their count).
fn write_tables_and_gallery(
    dir: &Path,
    map: &BoardMap,
    pads: &[Pad],
    i: &Inspection,
    program: &Program,
    report: &Value,
    names: Names,
) -> Result<usize, InspectError> {
    let Names { unit, recipe } = names;
    dpsa_formats::files::write_bytes(&dir.join("pads.csv"), csv(pads, i).as_bytes())?;
    dpsa_formats::files::write_bytes(
        &dir.join("report.json"),
        serde_json::to_string_pretty(report)?.as_bytes(),
    )?;
    let msg = cfx(pads, i, program, unit, recipe);
    dpsa_formats::files::write_bytes(
        &dir.join("cfx_units_inspected.json"),
        serde_json::to_string_pretty(&msg)?.as_bytes(),
    )?;
    let t = i.registration.transform;
    let gal = dir.join("gallery");
    std::fs::create_dir_all(&gal).map_err(|error| InspectError::CreateDir {
        path: gal.clone(),
        error,
    })?;
    let mut fails: Vec<usize> = (0..pads.len())
        .filter(|&k| i.calls[k].level == Level::Fail)
        .collect();
    fails.sort_by_key(|&k| (i.calls[k].class, k));
    let mut n = 0;
    for &k in fails.iter().take(MAX_GALLERY) {
        let class = i.calls[k].class.map(|c| c.name()).unwrap_or("fail");
        let name: String = cfx_pad(&pads[k])
            .chars()
            .map(|ch| {
                if ch.is_ascii_alphanumeric() || ch == '.' || ch == '-' {
                    ch
                } else {
                    '_'
                }
            })
            .collect();
        let img = defect_picture(map, &pads[k], &i.measurements[k], &i.calls[k], &t, program);
        dpsa_formats::images::save_png(&img, &gal.join(format!("{n:03}_{class}_{name}.png")))?;
        n += 1;
    }
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use dpsa_formats::grid::{BoardGrid, Grid};
    use dpsa_gerber::pads::Outline;

    /// The overview tests' board: 20 x 15 mm at 50 um.
    fn test_grid() -> BoardGrid {
        BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.05,
            rows: 400,
            width: 300,
        }
    }

    /// Board x runs to the right and y up: a failure at the board's right top shows there,
    /// ringed in red; a passing opening is outlined in green; a fiducial is ringed in cyan;
    /// the image has its margins.
    #[test]
    fn the_overview_is_the_design_view_with_its_calls_ringed() {
        let g = test_grid();
        let map = BoardMap {
            board_id: None,
            grid: g,
            heights: Grid {
                width: g.width,
                rows: g.rows,
                data: (0..g.rows * g.width).map(|k| (k % 7) as f32).collect(),
            },
        };
        let disc = |x: f64, y: f64| Outline::Circle {
            centre: [x, y],
            diameter: 1.0,
        };
        let marks = [
            Mark {
                outline: disc(18.0, 13.0),
                colour: [255, 30, 30],
                call: Some(("U1.1 insufficient".into(), true)),
            },
            Mark {
                outline: disc(3.0, 2.0),
                colour: [0, 200, 60],
                call: None,
            },
        ];
        let img = draw_overview(&map, &marks, &[[10.0, 7.5]], "board", 400);
        let fr = OverviewFrame::of(&g, 400);
        assert_eq!(fr.f, 1);
        assert_eq!(img.dimensions(), fr.image);
        assert_eq!(fr.image, (424, 396));
        // The failure: right (x 18 of 20 mm) and top (y 13 of 15 mm).
        let (x, y) = fr.pixel(&g, 18.0, 13.0);
        assert!(
            (x - 372.0).abs() < 1e-9 && (y - 80.0).abs() < 1e-9,
            "{x} {y}"
        );
        let red = |u: i64, v: i64| img.get_pixel(u as u32, v as u32).0 == [255, 30, 30];
        // Its ring (radius 9 px) and its outline (radius 10 px).
        assert!((-1..=1).any(|d| red(x as i64 + 9 + d, y as i64)), "no ring");
        assert!(
            (-1..=1).any(|d| red(x as i64, y as i64 - 10 + d)),
            "no outline"
        );
        // The passing opening: bottom left, outlined in green.
        let (x, y) = fr.pixel(&g, 3.0, 2.0);
        let green =
            (-1..=1).any(|d| img.get_pixel((x as i64 + 10 + d) as u32, y as u32).0 == [0, 200, 60]);
        assert!(green && y >= 300.0, "{x} {y}");
        // The fiducial's cyan ring.
        let (x, y) = fr.pixel(&g, 10.0, 7.5);
        let cyan = (-1..=1)
            .any(|d| img.get_pixel((x as i64 + 10 + d) as u32, y as u32).0 == [0, 210, 230]);
        assert!(cyan, "{x} {y}");
    }

    /// The heights in grey are above the board's local surface: on a board bowed by 300 um,
    /// the bare board is dark at its middle and at its corners alike, and a 100 um deposit
    /// is bright.
    #[test]
    fn the_overview_takes_out_the_bow() {
        let g = test_grid();
        let deposit = |x: f64, y: f64| (x - 10.0).abs() < 0.75 && (y - 7.5).abs() < 0.75;
        let data = (0..g.rows * g.width)
            .map(|k| {
                let (x, y) = g.centre(k / g.width, k % g.width);
                let (xi, eta) = (x / 10.0 - 1.0, y / 7.5 - 1.0);
                let bow = 300.0 * (1.0 - xi * xi) * (1.0 - eta * eta);
                (bow + if deposit(x, y) { 100.0 } else { 0.0 }) as f32
            })
            .collect();
        let map = BoardMap {
            board_id: None,
            grid: g,
            heights: Grid {
                width: g.width,
                rows: g.rows,
                data,
            },
        };
        let img = draw_overview(&map, &[], &[], "board", 400);
        let fr = OverviewFrame::of(&g, 400);
        let grey = |x: f64, y: f64| {
            let (u, v) = fr.pixel(&g, x, y);
            img.get_pixel(u as u32, v as u32).0[0]
        };
        assert!(grey(10.0, 7.5) > 180, "the deposit: {}", grey(10.0, 7.5));
        for (x, y) in [(5.0, 7.5), (1.0, 1.0), (19.0, 14.0), (10.0, 3.0)] {
            assert!(grey(x, y) < 60, "bare board at ({x}, {y}): {}", grey(x, y));
        }
    }
}
