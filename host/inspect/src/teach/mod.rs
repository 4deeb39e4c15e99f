//! `dpsa program`: the teach step. From a board's design files, the inspection program.
//!
//! | file | step |
//! | --- | --- |
//! | [`placement`] | pick-and-place files (KiCad `.pos` and CSV, Altium Pick Place, generic CSV) |
//! | [`names`] | every pad's component (nearest centre) and pin (X2, else reading order) |
//! | [`fiducials`] | round bare copper pads in a clear ring (or X2 `FiducialPad`) |
//! | `outline` | the board outline's box: the board corner |
//! | `families` | package families and their default windows, written as `[[override]]` |
//!
//! Nothing here needs the simulator. `docs/inspection.md`, "Teach: dpsa program", explains
//! each rule.

pub mod families;
pub mod fiducials;
pub mod names;
pub(crate) mod outline;
pub mod placement;

use crate::program::{Override, Program, ProgramError};
use dpsa_gerber::pads::Pad;
use dpsa_gerber::{self as gerber, GerberError};
use placement::{ComponentsFile, PlacementError, Side};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Why the teach step (or naming the pads at inspection) failed.
#[derive(Debug, thiserror::Error)]
pub enum TeachError {
    /// A Gerber layer could not be read. The reader's error is part of the message, not a
    /// `source()` (a chain printed in full would say it twice), and the file is named once.
    #[error("{what} {}", .error.in_file(std::path::Path::new(.path)))]
    Layer {
        /// `paste layer`, `copper layer` or `outline`.
        what: &'static str,
        /// The layer's file.
        path: String,
        /// The reader's error.
        error: GerberError,
    },
    /// The placement file could not be read (the reader's error in the message, the file
    /// named once).
    #[error("{}", placement_message(.path, .error))]
    Placement {
        /// The placement file.
        path: String,
        /// The reader's error.
        error: PlacementError,
    },
    /// Inputs that cannot make a program (a truncated or empty paste layer, an outline
    /// without a board edge, a path that is not UTF-8...), as one sentence.
    #[error("{0}")]
    Invalid(String),
    /// The program made does not validate.
    #[error(transparent)]
    Program(#[from] ProgramError),
}

/// What `dpsa program` is given.
#[derive(Clone, Debug)]
pub struct Inputs {
    /// The top paste layer (Gerber).
    pub paste: PathBuf,
    /// The top copper layer, where the fiducials are looked for (None: no fiducials, the
    /// program registers by the paste pattern).
    pub copper: Option<PathBuf>,
    /// The board outline (None: the paste layer's box stands for the board, with a warning).
    pub outline: Option<PathBuf>,
    /// The placement file and how to read it (`file` as given on the command line).
    pub components: Option<ComponentsFile>,
    /// Stencil thickness, um.
    pub stencil_um: f64,
    /// The program's (recipe's) name, if given.
    pub name: Option<String>,
    /// Where the program is written: the paths in it are relative to its directory.
    pub out: PathBuf,
}

/// What the teach step found, printed by `dpsa program`.
#[derive(Clone, Debug, Serialize)]
pub struct Summary {
    /// Pads of the paste layer.
    pub pads: usize,
    /// Pads per package family (`chip`, `qfn`, ...).
    pub families: BTreeMap<String, usize>,
    /// The fiducials found on the copper layer (none without one).
    pub fiducials: fiducials::Found,
    /// Whether a copper layer was given (no copper: no fiducials looked for).
    pub copper_given: bool,
    /// Pads with a component name (from the layer or the placement file).
    pub named: usize,
    /// Pads without a component: their names (`#index`) and centres, at most 50.
    pub unnamed: Vec<String>,
    /// Pads without a component, all of them.
    pub unnamed_count: usize,
    /// How the placement file named the pads (None without one).
    pub naming: Option<names::Naming>,
    /// `outline FILE` or `paste layer box (no outline)`.
    pub outline: String,
    /// The board edge's box, mm, design frame.
    pub board_box_mm: [f64; 4],
    /// The board corner (the box's low corner), design mm: the program's
    /// `placement.design_origin_mm`.
    pub design_origin_mm: [f64; 2],
    /// `[[override]]` entries written for the families.
    pub overrides: usize,
    /// What the program may lack (no outline, a paste layer outside the outline), one
    /// sentence each.
    pub warnings: Vec<String>,
}

/// The program and its summary.
#[derive(Clone, Debug)]
pub struct Taught {
    /// The program, validated.
    pub program: Program,
    /// What was found.
    pub summary: Summary,
}

/// A placement error as said of the file at `path`: named once (a reading error names it).
fn placement_message(path: &str, error: &PlacementError) -> String {
    match error {
        PlacementError::Read { .. } => error.to_string(),
        _ => format!("{path}: {error}"),
    }
}

fn layer(what: &'static str, path: &Path) -> Result<gerber::PasteLayer, TeachError> {
    gerber::read_file(path).map_err(|error| TeachError::Layer {
        what,
        path: path.display().to_string(),
        error,
    })
}

/// `file` as the program names it: relative to the program's directory when it lies inside
/// it, else absolute.
fn relative(out: &Path, file: &Path) -> Result<String, TeachError> {
    let abs = std::fs::canonicalize(file)
        .map_err(|e| TeachError::Invalid(format!("{}: {}", file.display(), e)))?;
    let dir = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let dir = std::fs::canonicalize(dir).map_err(|e| {
        TeachError::Invalid(format!("the program's directory {}: {e}", dir.display()))
    })?;
    let p = abs.strip_prefix(&dir).unwrap_or(&abs);
    p.to_str()
        .map(str::to_string)
        .ok_or_else(|| TeachError::Invalid(format!("{}: the path is not UTF-8", file.display())))
}

/// Reads the placement file and names the pads; the components' `(reference, package)` of
/// the top side come back for the packages' overrides.
fn name_pads(
    cf: &ComponentsFile,
    path: &Path,
    pads: &mut [Pad],
) -> Result<(names::Naming, Vec<(String, String)>), TeachError> {
    let comps = placement::read_file(path, cf).map_err(|error| TeachError::Placement {
        path: path.display().to_string(),
        error,
    })?;
    let naming = names::assign(pads, &comps, cf.max_distance_mm);
    let packages = comps
        .iter()
        .filter(|c| c.side == Side::Top)
        .filter_map(|c| Some((c.reference.clone(), c.package.clone()?)))
        .collect();
    Ok((naming, packages))
}

/// At inspection: names the pads from the program's `[components]` (the same rule as
/// `dpsa program`) and resolves its `package` overrides. Nothing without `[components]`.
pub fn apply_components(
    program: &mut Program,
    program_path: &Path,
    pads: &mut [Pad],
) -> Result<Option<names::Naming>, TeachError> {
    let (Some(cf), Some(path)) = (
        program.components.clone(),
        program.components_path(program_path),
    ) else {
        return Ok(None);
    };
    let (naming, packages) = name_pads(&cf, &path, pads)?;
    program.resolve_packages(&packages);
    Ok(Some(naming))
}

/// The package of each top-side component in the program's `[components]` placement file,
/// by reference (`U7` to `QFN-32`); empty without `[components]`.
pub fn component_packages(
    program: &Program,
    program_path: &Path,
) -> Result<BTreeMap<String, String>, TeachError> {
    let (Some(cf), Some(path)) = (
        program.components.as_ref(),
        program.components_path(program_path),
    ) else {
        return Ok(BTreeMap::new());
    };
    let comps = placement::read_file(&path, cf).map_err(|error| TeachError::Placement {
        path: path.display().to_string(),
        error,
    })?;
    Ok(comps
        .into_iter()
        .filter(|c| c.side == Side::Top)
        .filter_map(|c| Some((c.reference, c.package?)))
        .collect())
}

/// Each pad's package family, as SPC groups pads and the operator's pages count false calls:
/// its component's package from the placement file, else its aperture class (`C 0.25`, ...);
/// `None` for a pad with neither.
pub fn pad_families(
    program: &Program,
    program_path: &Path,
    pads: &[Pad],
) -> Result<Vec<Option<String>>, TeachError> {
    let packages = component_packages(program, program_path)?;
    Ok(pads
        .iter()
        .map(|p| {
            p.component
                .as_ref()
                .and_then(|c| packages.get(c).cloned())
                .or_else(|| p.aperture.clone())
        })
        .collect())
}

/// The family overrides: one per (package, aperture class) whose pads are all of one family
/// with its own defaults; pads of a mixed group get one override each (by name), first.
fn family_overrides(
    pads: &[Pad],
    fams: &[&'static str],
    packages: &BTreeMap<String, String>,
) -> Vec<Override> {
    let mut groups: BTreeMap<(Option<String>, Option<String>), Vec<usize>> = BTreeMap::new();
    for (i, p) in pads.iter().enumerate() {
        let pkg = p.component.as_ref().and_then(|c| packages.get(c)).cloned();
        groups.entry((pkg, p.aperture.clone())).or_default().push(i);
    }
    let mut single = Vec::new();
    let mut grouped = Vec::new();
    for ((pkg, ap), members) in groups {
        let f = fams[members[0]];
        if members.iter().all(|&i| fams[i] == f) && (pkg.is_some() || ap.is_some()) {
            if let Some(o) = families::default_override(f) {
                grouped.push(Override {
                    package: pkg,
                    aperture: ap,
                    ..o
                });
            }
        } else {
            for &i in &members {
                if let Some(o) = families::default_override(fams[i]) {
                    single.push(Override {
                        pad: Some(pads[i].name()),
                        ..o
                    });
                }
            }
        }
    }
    single.extend(grouped);
    single
}

/// The teach step (see the module's table).
pub fn teach(inp: &Inputs) -> Result<Taught, TeachError> {
    let mut warnings = Vec::new();
    let paste = layer("paste layer", &inp.paste)?;
    if !paste.complete {
        return Err(TeachError::Invalid(format!(
            "paste layer {}: the file has no end (M02) and may be truncated",
            inp.paste.display()
        )));
    }
    if paste.pads.is_empty() {
        return Err(TeachError::Invalid(format!(
            "paste layer {}: no pads",
            inp.paste.display()
        )));
    }
    let paste_box = paste.bbox_mm;
    let mut pads = paste.pads;
    // Names.
    let mut components = None;
    let (naming, packages) = match &inp.components {
        Some(cf) => {
            let path = PathBuf::from(&cf.file);
            let (n, pk) = name_pads(cf, &path, &mut pads)?;
            components = Some(ComponentsFile {
                file: relative(&inp.out, &path)?,
                ..cf.clone()
            });
            (Some(n), pk.into_iter().collect::<BTreeMap<_, _>>())
        }
        None => (None, BTreeMap::new()),
    };
    // Fiducials.
    let found = match &inp.copper {
        Some(path) => {
            let copper = layer("copper layer", path)?;
            // The reader is within its caps: the file was just read whole.
            let text = dpsa_formats::files::read_capped_io(path, gerber::MAX_FILE_BYTES)
                .map(|b| String::from_utf8_lossy(&b).into_owned())
                .unwrap_or_default();
            let x2 = fiducials::x2_fiducial_flashes(&text);
            fiducials::find(&copper.pads, &pads, &x2)
        }
        None => fiducials::Found::default(),
    };
    // Outline.
    let (outline, board_box) = match &inp.outline {
        Some(path) => {
            let l = layer("outline", path)?;
            match outline::board_box(&l) {
                Some(b) => (format!("outline {}", path.display()), b),
                None => {
                    return Err(TeachError::Invalid(format!(
                        "outline {}: it draws no board edge",
                        path.display()
                    )))
                }
            }
        }
        None => {
            warnings.push(
                "no --outline: the board corner is taken from the paste layer's box (inside the board by the margin without paste); give the outline (Edge.Cuts / profile) for the true corner".into(),
            );
            ("paste layer box (no outline)".into(), paste_box)
        }
    };
    if paste_box[0] < board_box[0] - 1e-6
        || paste_box[1] < board_box[1] - 1e-6
        || paste_box[2] > board_box[2] + 1e-6
        || paste_box[3] > board_box[3] + 1e-6
    {
        warnings.push(format!(
            "the paste layer's box {paste_box:?} is not inside the outline's {board_box:?}: is the outline of this board, in the same coordinates?"
        ));
    }
    // Families.
    let fams = families::classify(&pads, &packages);
    let mut per_family: BTreeMap<String, usize> = BTreeMap::new();
    for f in &fams {
        *per_family.entry((*f).to_string()).or_default() += 1;
    }
    let overrides = family_overrides(&pads, &fams, &packages);
    let unnamed: Vec<usize> = (0..pads.len())
        .filter(|&i| pads[i].component.is_none())
        .collect();
    let mut program = Program::new(relative(&inp.out, &inp.paste)?);
    program.name = inp.name.clone();
    program.stencil_um = inp.stencil_um;
    // To the nanometre: the file's coordinates, without the float noise of the conversion.
    let nm = |v: f64| (v * 1e6).round() / 1e6;
    let board_box = board_box.map(nm);
    program.placement.design_origin_mm = [board_box[0], board_box[1]];
    let mut found = found;
    for p in &mut found.points_mm {
        *p = p.map(nm);
    }
    found.diameter_mm = nm(found.diameter_mm);
    if !found.points_mm.is_empty() {
        program.fiducials.points_mm = found.points_mm.clone();
        program.fiducials.diameter_mm = found.diameter_mm;
    }
    program.components = components;
    program.overrides = overrides;
    program.validate()?;
    let summary = Summary {
        pads: pads.len(),
        families: per_family,
        fiducials: found,
        copper_given: inp.copper.is_some(),
        named: pads.len() - unnamed.len(),
        unnamed: unnamed
            .iter()
            .take(50)
            .map(|&i| {
                let c = pads[i].outline.centroid();
                format!("{} at ({:.3}, {:.3})", pads[i].name(), c[0], c[1])
            })
            .collect(),
        unnamed_count: unnamed.len(),
        naming,
        outline,
        board_box_mm: board_box,
        design_origin_mm: [board_box[0], board_box[1]],
        overrides: program.overrides.len(),
        warnings,
    };
    Ok(Taught { program, summary })
}

/// The program file's text: a comment head (what was found, and what is missing) and the
/// TOML.
pub fn program_text(t: &Taught) -> String {
    let s = &t.summary;
    let mut h = String::from("# Inspection program written by `dpsa program` (docs/inspection.md, \"Teach: dpsa program\").\n");
    h.push_str(&format!("# board corner from the {}\n", s.outline));
    if s.fiducials.points_mm.is_empty() {
        h.push_str(if s.copper_given {
            "# FIDUCIALS: NONE FOUND on the copper layer. `dpsa inspect` registers the design by its\n# paste pattern instead (docs/inspection.md); to register by fiducials, add their\n# design-frame centres to [fiducials] points_mm.\n"
        } else {
            "# FIDUCIALS: NONE (no --copper layer given). `dpsa inspect` registers the design by its\n# paste pattern instead (docs/inspection.md); to register by fiducials, add their\n# design-frame centres to [fiducials] points_mm.\n"
        });
    } else {
        h.push_str(&format!(
            "# fiducials: {} found on the copper layer, diameter {} mm\n",
            s.fiducials.points_mm.len(),
            s.fiducials.diameter_mm
        ));
    }
    h.push_str(&format!(
        "# pads: {}, named {}, without a name {}\n",
        s.pads, s.named, s.unnamed_count
    ));
    h.push_str("# [[override]] entries: the package families' default windows (edit freely)\n\n");
    h + &t.program.to_toml_string()
}
