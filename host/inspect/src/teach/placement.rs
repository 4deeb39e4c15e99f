//! Pick-and-place (centroid) files: where each component sits, its rotation, side and package.
//!
//! | format | what it looks like |
//! | --- | --- |
//! | `kicad` | KiCad's ASCII `.pos`: `#` comment lines (`## Unit = mm` or `inches`), then `Ref Val Package PosX PosY Rot Side` separated by blanks |
//! | `kicad-csv` | KiCad's CSV: the header `Ref,Val,Package,PosX,PosY,Rot,Side`, mm |
//! | `altium` | Altium's Pick Place (`.csv` or `.txt`): free text lines, a `Units used` line, then a header with `Designator`, `Mid X`, `Mid Y` (or `Center-X(mm)`...), `Rotation`, `Layer`, `Footprint`; values may carry `mm` or `mil` |
//! | `csv` | any CSV with a header, read through a column mapping (`ref`, `x`, `y`, and optionally `rot`, `side`, `package`) and a unit |
//!
//! Only top-side components are kept (a file without a side column is all top). The file is
//! read whole, at most [`MAX_PLACEMENT_BYTES`], with at most [`MAX_COMPONENTS`] rows.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// Largest placement file read, bytes.
pub const MAX_PLACEMENT_BYTES: u64 = 16 << 20;
/// Most components in one file.
pub const MAX_COMPONENTS: usize = 200_000;

/// Why a placement file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum PlacementError {
    /// The file could not be read (missing, not a regular file, larger than
    /// [`MAX_PLACEMENT_BYTES`]).
    #[error("cannot read the placement file {path}: {cause}")]
    Read {
        /// The placement file.
        path: String,
        /// The reading error's text.
        cause: String,
    },
    /// A line that does not read.
    #[error("placement file, line {line}: {message}")]
    Line {
        /// 1-based line number.
        line: usize,
        /// What is wrong with it.
        message: String,
    },
    /// The file as a whole (no header, no components, one listed twice, an unknown unit...).
    #[error("placement file: {0}")]
    Format(String),
}

fn at(line: usize, message: impl Into<String>) -> PlacementError {
    PlacementError::Line {
        line,
        message: message.into(),
    }
}

/// The placement file's format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Format {
    /// KiCad's ASCII `.pos`.
    Kicad,
    /// KiCad's CSV.
    KicadCsv,
    /// Altium's Pick Place.
    Altium,
    /// Any CSV, through [`Columns`].
    Csv,
}

impl std::str::FromStr for Format {
    type Err = String;
    fn from_str(s: &str) -> Result<Format, String> {
        match s {
            "kicad" => Ok(Format::Kicad),
            "kicad-csv" => Ok(Format::KicadCsv),
            "altium" => Ok(Format::Altium),
            "csv" => Ok(Format::Csv),
            _ => Err(format!(
                "unknown placement format {s:?}: kicad, kicad-csv, altium or csv"
            )),
        }
    }
}

/// The columns of a generic CSV: header names (exact, case-insensitive).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Columns {
    /// The component reference's column (`ref`).
    #[serde(rename = "ref")]
    pub reference: String,
    /// The centre's x column.
    pub x: String,
    /// The centre's y column.
    pub y: String,
    /// The rotation's column, degrees (None: every rotation 0).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rot: Option<String>,
    /// The side's column (None: every component on top).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub side: Option<String>,
    /// The package's column (None: no packages).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub package: Option<String>,
}

impl std::str::FromStr for Columns {
    type Err = String;
    /// `ref=Designator,x=Mid X,y=Mid Y,rot=Rotation,side=Layer,package=Footprint`.
    fn from_str(s: &str) -> Result<Columns, String> {
        let mut c = Columns::default();
        for part in s.split(',') {
            let (k, v) = part
                .split_once('=')
                .ok_or_else(|| format!("--columns: {part:?} is not key=COLUMN"))?;
            let v = v.trim().to_string();
            match k.trim() {
                "ref" => c.reference = v,
                "x" => c.x = v,
                "y" => c.y = v,
                "rot" => c.rot = Some(v),
                "side" => c.side = Some(v),
                "package" => c.package = Some(v),
                k => {
                    return Err(format!(
                        "--columns: unknown key {k:?} (ref, x, y, rot, side, package)"
                    ))
                }
            }
        }
        if c.reference.is_empty() || c.x.is_empty() || c.y.is_empty() {
            return Err("--columns needs at least ref=, x= and y=".into());
        }
        Ok(c)
    }
}

/// How the program names its pads from a placement file (`[components]` of the program).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ComponentsFile {
    /// The placement file, relative to the program.
    pub file: String,
    /// How the file is written.
    pub format: Format,
    /// Generic CSV only: which column is what.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub columns: Option<Columns>,
    /// Generic CSV only: the unit of its coordinates, `mm`, `mil` or `inch` (default mm).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub units: Option<String>,
    /// A pad is given to the nearest component centre within this distance, mm.
    #[serde(default = "default_max_distance")]
    pub max_distance_mm: f64,
}

/// The default of [`ComponentsFile::max_distance_mm`]: 8 mm.
pub fn default_max_distance() -> f64 {
    8.0
}

/// The side a component is placed on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub(crate) enum Side {
    Top,
    Bottom,
}

/// One component of a placement file.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub(crate) struct Component {
    pub reference: String,
    /// Centre (the file's position), mm, in the design (Gerber) frame.
    pub at_mm: [f64; 2],
    pub rotation_deg: f64,
    pub side: Side,
    pub package: Option<String>,
}

/// Reads a placement file; top and bottom components both, in file order.
pub(crate) fn read_file(
    path: &Path,
    cf: &ComponentsFile,
) -> Result<Vec<Component>, PlacementError> {
    let bytes = dpsa_formats::files::read_capped_io(path, MAX_PLACEMENT_BYTES).map_err(|e| {
        PlacementError::Read {
            path: path.display().to_string(),
            cause: dpsa_formats::files::io_cause(&e),
        }
    })?;
    // Altium writes Windows-1252: a non-UTF-8 file is read as Latin-1.
    let text = match String::from_utf8(bytes) {
        Ok(t) => t,
        Err(e) => e.into_bytes().into_iter().map(char::from).collect(),
    };
    parse(&text, cf)
}

/// Parses a placement file's text.
pub(crate) fn parse(text: &str, cf: &ComponentsFile) -> Result<Vec<Component>, PlacementError> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let out = match cf.format {
        Format::Kicad => parse_kicad(text)?,
        Format::KicadCsv => {
            let cols = Columns {
                reference: "Ref".into(),
                x: "PosX".into(),
                y: "PosY".into(),
                rot: Some("Rot".into()),
                side: Some("Side".into()),
                package: Some("Package".into()),
            };
            parse_table(text, &cols, Unit::Fixed(1.0), 0)?
        }
        Format::Altium => parse_altium(text)?,
        Format::Csv => {
            let cols = cf.columns.as_ref().ok_or_else(|| {
                PlacementError::Format(
                    "a generic CSV needs its columns (--columns ref=..,x=..,y=..)".into(),
                )
            })?;
            let scale = match cf.units.as_deref().unwrap_or("mm") {
                "mm" => 1.0,
                "mil" => 0.0254,
                "inch" | "in" => 25.4,
                u => {
                    return Err(PlacementError::Format(format!(
                        "unknown unit {u:?}: mm, mil or inch"
                    )))
                }
            };
            parse_table(text, cols, Unit::Fixed(scale), 0)?
        }
    };
    if out.is_empty() {
        return Err(PlacementError::Format("no components in the file".into()));
    }
    let mut seen = std::collections::HashSet::new();
    for c in &out {
        if c.side == Side::Top && !seen.insert(c.reference.as_str()) {
            return Err(PlacementError::Format(format!(
                "component {} is listed twice on the top side",
                c.reference
            )));
        }
    }
    Ok(out)
}

fn number(line: usize, what: &str, s: &str) -> Result<f64, PlacementError> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|_| at(line, format!("{what} {s:?} is not a number")))?;
    if !v.is_finite() || v.abs() > 10_000.0 {
        return Err(at(
            line,
            format!("{what} {s:?} is out of range (|v| <= 10 m)"),
        ));
    }
    Ok(v)
}

fn side_of(line: usize, s: &str) -> Result<Side, PlacementError> {
    match s.trim().to_ascii_lowercase().as_str() {
        "top" | "t" | "toplayer" | "top layer" | "f.cu" | "front" => Ok(Side::Top),
        "bottom" | "b" | "bottomlayer" | "bottom layer" | "b.cu" | "back" => Ok(Side::Bottom),
        _ => Err(at(line, format!("side {s:?} is neither top nor bottom"))),
    }
}

fn push(out: &mut Vec<Component>, line: usize, c: Component) -> Result<(), PlacementError> {
    if out.len() >= MAX_COMPONENTS {
        return Err(at(line, format!("more than {MAX_COMPONENTS} components")));
    }
    if c.reference.is_empty() {
        return Err(at(line, "empty reference"));
    }
    out.push(c);
    Ok(())
}

fn parse_kicad(text: &str) -> Result<Vec<Component>, PlacementError> {
    let mut scale = None;
    let mut out = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let n = i + 1;
        let l = raw.trim();
        if l.is_empty() {
            continue;
        }
        if let Some(c) = l.strip_prefix('#') {
            let c = c.trim_start_matches('#').trim();
            if let Some(u) = c.strip_prefix("Unit") {
                let u = u.trim_start_matches([' ', '=']).to_ascii_lowercase();
                scale = Some(if u.starts_with("mm") {
                    1.0
                } else if u.starts_with("inch") {
                    25.4
                } else {
                    return Err(at(n, format!("unknown unit {u:?}")));
                });
            }
            continue;
        }
        let t: Vec<&str> = l.split_whitespace().collect();
        if t.len() < 7 {
            return Err(at(
                n,
                "expected Ref Val Package PosX PosY Rot Side (7 fields)",
            ));
        }
        let k = t.len();
        let s = scale.ok_or_else(|| at(n, "no `## Unit = mm` (or inches) line before the data"))?;
        push(
            &mut out,
            n,
            Component {
                reference: t[0].to_string(),
                at_mm: [
                    number(n, "PosX", t[k - 4])? * s,
                    number(n, "PosY", t[k - 3])? * s,
                ],
                rotation_deg: number(n, "Rot", t[k - 2])?,
                side: side_of(n, t[k - 1])?,
                package: Some(t[k - 5].to_string()),
            },
        )?;
    }
    Ok(out)
}

/// Splits one CSV (or blank-separated, when `sep` is None) line, with double quotes.
fn split(line: &str, sep: Option<char>) -> Vec<String> {
    let mut out = Vec::new();
    let mut cur = String::new();
    let mut quoted = false;
    let mut any = false;
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        if quoted {
            if c == '"' {
                if chars.peek() == Some(&'"') {
                    cur.push('"');
                    chars.next();
                } else {
                    quoted = false;
                }
            } else {
                cur.push(c);
            }
            continue;
        }
        let is_sep = match sep {
            Some(s) => c == s,
            None => c.is_whitespace(),
        };
        if c == '"' {
            quoted = true;
            any = true;
        } else if is_sep {
            if sep.is_some() || any || !cur.is_empty() {
                out.push(std::mem::take(&mut cur).trim().to_string());
            }
            any = false;
        } else {
            cur.push(c);
        }
    }
    if sep.is_some() || any || !cur.is_empty() {
        out.push(cur.trim().to_string());
    }
    out
}

/// How a table's coordinates are scaled to mm.
#[derive(Clone, Copy)]
enum Unit {
    /// Plain numbers times this.
    Fixed(f64),
    /// Numbers may end in `mm` or `mil`; plain ones times this.
    Suffixed(f64),
}

fn length(line: usize, what: &str, s: &str, unit: Unit) -> Result<f64, PlacementError> {
    let s = s.trim();
    match unit {
        Unit::Fixed(k) => Ok(number(line, what, s)? * k),
        Unit::Suffixed(k) => {
            let low = s.to_ascii_lowercase();
            if let Some(v) = low.strip_suffix("mm") {
                Ok(number(line, what, v)?)
            } else if let Some(v) = low.strip_suffix("mil") {
                Ok(number(line, what, v)? * 0.0254)
            } else {
                Ok(number(line, what, s)? * k)
            }
        }
    }
}

/// A table with a header line at `header` (0-based line index) or the first non-empty line.
fn parse_table(
    text: &str,
    cols: &Columns,
    unit: Unit,
    header: usize,
) -> Result<Vec<Component>, PlacementError> {
    let lines: Vec<&str> = text.lines().collect();
    let h = (header..lines.len())
        .find(|&i| !lines[i].trim().is_empty())
        .ok_or_else(|| PlacementError::Format("no header line".into()))?;
    let sep = if lines[h].contains(',') {
        Some(',')
    } else if lines[h].contains(';') {
        Some(';')
    } else if lines[h].contains('\t') {
        Some('\t')
    } else {
        None
    };
    let names = split(lines[h], sep);
    let index: BTreeMap<String, usize> = names
        .iter()
        .enumerate()
        .map(|(i, n)| (n.to_ascii_lowercase(), i))
        .collect();
    let col = |name: &str| -> Result<usize, PlacementError> {
        index
            .get(&name.to_ascii_lowercase())
            .copied()
            .ok_or_else(|| {
                at(
                    h + 1,
                    format!(
                        "no column {name:?} in the header (columns: {})",
                        names.join(", ")
                    ),
                )
            })
    };
    let (r, x, y) = (col(&cols.reference)?, col(&cols.x)?, col(&cols.y)?);
    let rot = cols.rot.as_deref().map(col).transpose()?;
    let side = cols.side.as_deref().map(col).transpose()?;
    let package = cols.package.as_deref().map(col).transpose()?;
    let mut out = Vec::new();
    for (i, l) in lines.iter().enumerate().skip(h + 1) {
        let n = i + 1;
        if l.trim().is_empty() {
            continue;
        }
        let f = split(l, sep);
        let get = |c: usize| -> Result<&str, PlacementError> {
            f.get(c).map(String::as_str).ok_or_else(|| {
                at(
                    n,
                    format!("{} fields, the header has {}", f.len(), names.len()),
                )
            })
        };
        push(
            &mut out,
            n,
            Component {
                reference: get(r)?.to_string(),
                at_mm: [
                    length(n, &names[x], get(x)?, unit)?,
                    length(n, &names[y], get(y)?, unit)?,
                ],
                rotation_deg: match rot {
                    Some(c) => number(n, &names[c], get(c)?)?,
                    None => 0.0,
                },
                side: match side {
                    Some(c) => side_of(n, get(c)?)?,
                    None => Side::Top,
                },
                package: package
                    .map(|c| get(c).map(str::to_string))
                    .transpose()?
                    .filter(|p| !p.is_empty()),
            },
        )?;
    }
    Ok(out)
}

fn parse_altium(text: &str) -> Result<Vec<Component>, PlacementError> {
    let lines: Vec<&str> = text.lines().collect();
    // The unit of plain numbers: the `Units used` line (default mil, Altium's own default).
    let mut k = 0.0254;
    let mut header = None;
    for (i, l) in lines.iter().enumerate() {
        let low = l.to_ascii_lowercase();
        if low.contains("units used") {
            let rest = low.split("units used").nth(1).unwrap_or("");
            if rest.contains("mm") {
                k = 1.0;
            } else if rest.contains("mil") {
                k = 0.0254;
            } else {
                return Err(at(i + 1, format!("unknown unit in {:?}", l.trim())));
            }
        }
        if low.contains("designator") && (low.contains("mid x") || low.contains("center-x")) {
            header = Some(i);
            break;
        }
    }
    let h = header.ok_or_else(|| {
        PlacementError::Format(
            "no Altium header line (Designator, Mid X, Mid Y, ...) in the file".into(),
        )
    })?;
    let low = lines[h].to_ascii_lowercase();
    let (x, y) = if low.contains("mid x") {
        ("Mid X", "Mid Y")
    } else if low.contains("center-x(mm)") {
        k = 1.0;
        ("Center-X(mm)", "Center-Y(mm)")
    } else {
        k = 0.0254;
        ("Center-X(mil)", "Center-Y(mil)")
    };
    let cols = Columns {
        reference: "Designator".into(),
        x: x.into(),
        y: y.into(),
        rot: Some("Rotation".into()),
        side: Some("Layer".into()),
        package: Some("Footprint".into()),
    };
    parse_table(text, &cols, Unit::Suffixed(k), h)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cf(format: Format) -> ComponentsFile {
        ComponentsFile {
            file: "x".into(),
            format,
            columns: None,
            units: None,
            max_distance_mm: 8.0,
        }
    }

    #[test]
    fn kicad_ascii_in_inches_and_mm() {
        let t = "### Module positions ###\n## Unit = inches, Angle = deg.\n## Side : top\n# Ref Val Package PosX PosY Rot Side\nC1 100n C_0603 1.0000 -0.5000 90.0000 top\nU2 \"MCU\" QFN-32 2.5 0.25 0 bottom\n## End\n";
        let c = parse(t, &cf(Format::Kicad)).unwrap();
        assert_eq!(c.len(), 2);
        assert_eq!(c[0].reference, "C1");
        assert!((c[0].at_mm[0] - 25.4).abs() < 1e-9 && (c[0].at_mm[1] + 12.7).abs() < 1e-9);
        assert_eq!(c[0].rotation_deg, 90.0);
        assert_eq!(c[0].package.as_deref(), Some("C_0603"));
        assert_eq!(c[1].side, Side::Bottom);
        // No unit line: refused, naming the line.
        let e = parse("C1 1 P 1 2 0 top\n", &cf(Format::Kicad)).unwrap_err();
        assert!(e.to_string().contains("line 1"), "{e}");
        let e = parse("## Unit = mm\nC1 1 P x 2 0 top\n", &cf(Format::Kicad)).unwrap_err();
        assert!(e.to_string().contains("PosX"), "{e}");
        let e = parse("## Unit = mm\nC1 1 P 1 2 0 left\n", &cf(Format::Kicad)).unwrap_err();
        assert!(e.to_string().contains("left"), "{e}");
    }

    #[test]
    fn kicad_csv_and_generic_csv() {
        let t = "Ref,Val,Package,PosX,PosY,Rot,Side\n\"R1\",\"10k\",\"R_0402_1005Metric\",100.5,-50.25,180.0,top\n";
        let c = parse(t, &cf(Format::KicadCsv)).unwrap();
        assert_eq!(c[0].at_mm, [100.5, -50.25]);
        assert_eq!(c[0].package.as_deref(), Some("R_0402_1005Metric"));
        let mut g = cf(Format::Csv);
        g.columns = Some("ref=Part,x=X,y=Y,side=Where".parse().unwrap());
        g.units = Some("mil".into());
        let t = "Part;X;Y;Where\nQ1;1000;-2000;T\nQ2;0;0;B\n";
        let c = parse(t, &g).unwrap();
        assert!((c[0].at_mm[0] - 25.4).abs() < 1e-9 && (c[0].at_mm[1] + 50.8).abs() < 1e-9);
        assert_eq!((c[0].side, c[1].side), (Side::Top, Side::Bottom));
        assert_eq!(c[0].rotation_deg, 0.0);
        // A missing column is named.
        g.columns = Some("ref=Part,x=Xpos,y=Y".parse().unwrap());
        let e = parse(t, &g).unwrap_err();
        assert!(e.to_string().contains("Xpos"), "{e}");
        // Duplicated reference on the top side.
        let t = "Ref,Val,Package,PosX,PosY,Rot,Side\nR1,1,P,1,1,0,top\nR1,1,P,2,2,0,top\n";
        assert!(parse(t, &cf(Format::KicadCsv)).is_err());
    }

    #[test]
    fn altium_pick_place_in_mil_and_mm() {
        let t = "Altium Designer Pick and Place Locations\r\nC:\\proj\\board.PcbDoc\r\n\r\n========================\r\nUnits used:          mil\r\n\r\n\"Designator\",\"Footprint\",\"Mid X\",\"Mid Y\",\"Ref X\",\"Ref Y\",\"Pad X\",\"Pad Y\",\"Layer\",\"Rotation\",\"Comment\"\r\n\"C1\",\"0603\",\"1000mil\",\"500mil\",\"1000mil\",\"500mil\",\"1030mil\",\"500mil\",\"T\",\"270\",\"100nF, 16 V\"\r\n\"U1\",\"SOIC8\",\"2000\",\"100\",\"0\",\"0\",\"0\",\"0\",\"B\",\"0\",\"\"\r\n";
        let c = parse(t, &cf(Format::Altium)).unwrap();
        assert_eq!(c.len(), 2);
        assert!((c[0].at_mm[0] - 25.4).abs() < 1e-9 && (c[0].at_mm[1] - 12.7).abs() < 1e-9);
        assert_eq!(c[0].rotation_deg, 270.0);
        assert_eq!(c[0].package.as_deref(), Some("0603"));
        assert!((c[1].at_mm[0] - 50.8).abs() < 1e-9);
        assert_eq!(c[1].side, Side::Bottom);
        let t = "Units used:,mm\n\"Designator\",\"Mid X\",\"Mid Y\",\"Layer\",\"Rotation\",\"Footprint\"\n\"R7\",\"12.5mm\",\"3\",\"TopLayer\",\"90\",\"0402\"\n";
        let c = parse(t, &cf(Format::Altium)).unwrap();
        assert_eq!(c[0].at_mm, [12.5, 3.0]);
        assert_eq!(c[0].side, Side::Top);
        assert!(parse("no header here\n", &cf(Format::Altium)).is_err());
    }
}
