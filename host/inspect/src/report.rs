//! The files of `dpsa inspect --out DIR`:
//!
//! | file | what |
//! | --- | --- |
//! | `pads.csv` | one row per pad; the IPC-CFX `SolderPasteMeasurement` names where they exist (`ComponentPad`, `PasteVolume`, `PasteHeight`, `PasteXOffset`, `PasteYOffset`, `Result`), then ours |
//! | `report.json` | what `--json` prints |
//! | `cfx_units_inspected.json` | an IPC-CFX 1.x `UnitsInspected` message (JSON envelope, `InspectionMethod` SPI), one `SolderPasteMeasurement` per pad, the failures as `DefectsFound` |
//! | `overview.png` | the board's heights in grey with every opening outlined in its verdict's colour: green pass, amber warning, red failure, magenta not measurable |
//! | `gallery/NNN_class_pad.png` | every failure (at most [`MAX_GALLERY`]): the heights above the pad's local surface around it (false colour, 0 to 1.6 x stencil, the opening outlined in white) over a profile through the opening's centre along the board's x (the stencil thickness dashed) |

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

/// `overview.png`: at most `max_px` pixels on the longer side (the map decimated by a whole
/// factor), the openings put on the board by `t`.
pub fn overview(
    map: &BoardMap,
    pads: &[Pad],
    t: &Rigid,
    i: &Inspection,
    max_px: usize,
) -> RgbImage {
    let g = &map.grid;
    let f = g.rows.max(g.width).div_ceil(max_px.max(1)).max(1);
    let (h, w) = (g.rows.div_ceil(f), g.width.div_ceil(f));
    let (lo, hi) = dpsa_formats::board_map::colour_range(&map.heights).unwrap_or((0.0, 1.0));
    let span = (hi - lo).max(1e-3);
    let mut img: RgbImage = ImageBuffer::from_pixel(w as u32, h as u32, Rgb([30, 30, 60]));
    for y in 0..h {
        for x in 0..w {
            let v = map.heights.at(y * f, x * f);
            if v.is_finite() {
                let q = (((v - lo) / span).clamp(0.0, 1.0) * 220.0 + 20.0) as u8;
                img.put_pixel(x as u32, y as u32, Rgb([q, q, q]));
            }
        }
    }
    let step = g.pitch_mm * f as f64;
    for ((p, m), c) in pads.iter().zip(&i.measurements).zip(&i.calls) {
        let o = p.outline.transformed(t);
        let b = o.bbox();
        let col = level_colour(c, m);
        let (ri, rj) = map.window([b[0] - step, b[1] - step, b[2] + step, b[3] + step]);
        let (y0, y1) = (ri.start / f, ri.end.div_ceil(f).min(h));
        let (x0, x1) = (rj.start / f, rj.end.div_ceil(f).min(w));
        // Failures get a thicker outline (the deposit stays visible inside).
        let width = if c.level == Level::Fail { 1.6 } else { 0.6 };
        for y in y0..y1 {
            for x in x0..x1 {
                let px = g.x0_mm + (y as f64 + 0.5) * step;
                let py = g.y0_mm + (x as f64 + 0.5) * step;
                let d = o.signed_distance([px, py]);
                if d.abs() <= width * step {
                    img.put_pixel(x as u32, y as u32, Rgb(col));
                }
            }
        }
    }
    img
}

/// One defect picture: the crop over the profile.
pub(crate) fn defect_picture(
    map: &BoardMap,
    p: &Pad,
    m: &PadMeasurement,
    t: &Rigid,
    stencil: f64,
) -> RgbImage {
    let o = p.outline.transformed(t);
    let b = o.bbox();
    let pad_mm = 0.6;
    let (ri, rj) = map.window([b[0] - pad_mm, b[1] - pad_mm, b[2] + pad_mm, b[3] + pad_mm]);
    let (ch, cw) = (ri.len().max(1), rj.len().max(1));
    let s = (240 / ch.max(cw)).clamp(1, 12);
    let (iw, crop_h, prof_h) = (cw * s, ch * s, 120usize);
    let mut img: RgbImage = ImageBuffer::from_pixel(
        iw as u32,
        (crop_h + prof_h + 4) as u32,
        Rgb([255, 255, 255]),
    );
    let c = o.centroid();
    let base = |x: f64, y: f64| crate::measure::surface_at(&m.surface, x - c[0], y - c[1]);
    let top = 1.6 * stencil;
    for (a, i) in ri.clone().enumerate() {
        for (bq, j) in rj.clone().enumerate() {
            let v = map.heights.data[i * map.grid.width + j];
            let (x, y) = map.grid.centre(i, j);
            let col = if v.is_finite() {
                dpsa_formats::images::colour(((f64::from(v) - base(x, y)) / top).clamp(0.0, 1.0))
            } else {
                [40, 40, 40]
            };
            let edge = o.signed_distance([x, y]).abs() <= 0.5 * map.grid.pitch_mm;
            for u in 0..s {
                for w in 0..s {
                    let px = if edge && (u + w) % 2 == 0 {
                        [255, 255, 255]
                    } else {
                        col
                    };
                    img.put_pixel((bq * s + w) as u32, (a * s + u) as u32, Rgb(px));
                }
            }
        }
    }
    // Profile along the board's x at the opening's centre column (image rows of the crop).
    let (_, jc) = map.pixel_of(c);
    let y0 = crop_h + 4;
    let to_y = |h: f64| {
        let t = (h / top).clamp(-0.1, 1.0);
        (y0 + prof_h - 1) as f64 - (t + 0.1) / 1.1 * (prof_h - 1) as f64
    };
    for xpix in (0..iw).step_by(6) {
        let yy = to_y(stencil).round() as u32;
        img.put_pixel(xpix as u32, yy, Rgb([120, 120, 120]));
    }
    let horizontal = ch; // samples along the profile
    let mut last: Option<(u32, u32)> = None;
    for (a, i) in ri.clone().enumerate() {
        if jc < 0 || jc as usize >= map.grid.width {
            break;
        }
        let v = map.heights.data[i * map.grid.width + jc as usize];
        if !v.is_finite() {
            last = None;
            continue;
        }
        let (x, y) = map.grid.centre(i, jc as usize);
        let xp = ((a as f64 + 0.5) / horizontal as f64 * iw as f64) as u32;
        let yp = to_y(f64::from(v) - base(x, y)).round() as u32;
        if let Some((lx, ly)) = last {
            let n = lx.abs_diff(xp).max(ly.abs_diff(yp)).max(1);
            for k in 0..=n {
                let xx = lx as f64 + (f64::from(xp) - f64::from(lx)) * f64::from(k) / f64::from(n);
                let yy = ly as f64 + (f64::from(yp) - f64::from(ly)) * f64::from(k) / f64::from(n);
                img.put_pixel(xx as u32, yy as u32, Rgb([0, 0, 0]));
            }
        }
        last = Some((xp, yp));
    }
    img
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
                &overview(map, pads, &t, i, 2400),
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
        let img = defect_picture(map, &pads[k], &i.measurements[k], &t, program.stencil_um);
        dpsa_formats::images::save_png(&img, &gal.join(format!("{n:03}_{class}_{name}.png")))?;
        n += 1;
    }
    Ok(n)
}
