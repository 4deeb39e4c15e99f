//! The inspection program (`program.toml`): what to measure and how to judge it.
//!
//! Every key has a documented default; only `paste_layer` is required. Lengths are mm, heights
//! um, percentages are of the opening's own figure (area x stencil thickness for volume, the
//! opening area for area, the stencil thickness for height, the opening's size along the axis
//! for offset).
//!
//! ```toml
//! paste_layer = "paste.gbr"        # relative to this file
//! allow_truncated_layer = false    # inspect a paste layer without its M02 end (reported)
//! stencil_um = 100.0
//!
//! [placement]                      # where the design lands on the conveyor (nominal)
//! design_origin_mm = [0.0, 0.0]    # the design point at the board corner
//! orientation_deg = 0.0            # the board turned on the conveyor: 0, 90, 180, 270
//!
//! [fiducials]
//! points_mm = [[3.0, 3.0], [217.0, 3.0], [3.0, 165.0]]   # design frame
//! diameter_mm = 1.0
//! search_mm = 1.5                  # how far from the nominal place to look
//!
//! [measure]
//! area_threshold_pct = 30.0        # paste = above this share of the stencil thickness
//! shape_threshold_um = 10.0        # paste for the shape (smear) measure
//! min_coverage = 0.85              # below: "not measurable"
//!
//! [reflectance]                    # how paste reflects against the board (the map's walls)
//! background_step = 0.0            # (B_paste - B_board) / C_board as the cameras see them
//!
//! [windows]                        # the default window of every pad
//! volume_pct = { warn = [65.0, 135.0], fail = [55.0, 145.0] }
//! # ... area_pct, height_pct, offset_pct, shape_pct, missing_pct, bridge_height_pct
//! guard_band_k = 2.0               # value +- k u straddling a fail limit: "warn: uncertain"
//!
//! [components]                     # pad names from a pick-and-place file (`dpsa program`)
//! file = "board-top.pos"           # relative to this file
//! format = "kicad"                 # kicad, kicad-csv, altium, csv (+ columns, units)
//! max_distance_mm = 8.0            # a pad goes to the nearest component centre within this
//!
//! [[override]]                     # per pad class, component or package (first match wins)
//! component = "U7"                 # or: aperture = "C 0.25" (the pad class), pad = "U7-3",
//!                                  # package = "QFN-32" (needs [components])
//! volume_pct = { warn = [60.0, 140.0], fail = [50.0, 150.0] }
//! ```

use dpsa_gerber::pads::{Point, Rigid};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Largest program file read, bytes.
pub const MAX_PROGRAM_BYTES: u64 = 4 << 20;

/// Why a program could not be read or is refused.
#[derive(Debug, thiserror::Error)]
pub enum ProgramError {
    /// The file could not be read (missing, not a regular file, larger than
    /// [`MAX_PROGRAM_BYTES`]).
    #[error("cannot read the program {path}: {cause}")]
    Read {
        /// The program file.
        path: PathBuf,
        /// The reading error's text.
        cause: String,
    },
    /// The file is not UTF-8, not TOML, or has a key the program does not know.
    #[error("the program {path} is not valid TOML or has unknown keys: {cause}")]
    Parse {
        /// The program file.
        path: PathBuf,
        /// The parser's text.
        cause: String,
    },
    /// A value out of its range ([`Program::validate`]).
    #[error("the program's {key} is {why}")]
    Invalid {
        /// The key, dotted (`windows.volume_pct`, `override[2].area_pct`).
        key: String,
        /// What is wrong with it, with the value.
        why: String,
    },
}

/// A lower and an upper limit, `[lo, hi]`.
pub type Limits = [f64; 2];

/// A two-sided window: outside `warn` is a warning, outside `fail` a failure.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Window {
    /// Inside `[lo, hi]` passes; outside is at least a warning.
    pub warn: Limits,
    /// Outside `[lo, hi]` fails; contains `warn`.
    pub fail: Limits,
}

/// A one-sided limit (offset, shape): above `warn` a warning, above `fail` a failure.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Upper {
    /// Above this, a warning (> 0).
    pub warn: f64,
    /// Above this, a failure (>= `warn`, at most 1000).
    pub fail: f64,
}

/// The tolerance windows of one pad.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Windows {
    /// Volume, % of opening area x stencil thickness. The fail levels sit 5 points inside the
    /// usual 50..150 % specification: a guard band of about twice the gauge's volume error on
    /// small openings, so that a deposit at the limit is not passed by measurement error.
    pub volume_pct: Window,
    /// Area above the paste threshold, % of the opening area.
    pub area_pct: Window,
    /// Mean height over the opening, % of the stencil thickness.
    pub height_pct: Window,
    /// Offset of the deposit's centre from the opening's along either axis, % of the
    /// opening's width (its smaller size).
    pub offset_pct: Upper,
    /// Paste (above `shape_threshold_um`) outside the opening grown by the wall, % of the
    /// opening area: smears and misshapen deposits.
    pub shape_pct: Upper,
    /// Below this volume % the pad is "missing" rather than "insufficient".
    pub missing_pct: f64,
    /// A bridge is paste above this % of the stencil thickness joining two openings.
    pub bridge_height_pct: f64,
    /// Guard band: a volume or height whose interval `value +- guard_band_k x u` (u its
    /// stated standard uncertainty) straddles a failure limit is called "warn: uncertain"
    /// instead of a pass or a fail that the measurement cannot back. 2 (about 95 %) by
    /// default; 0 turns it off.
    pub guard_band_k: f64,
}

impl Default for Windows {
    fn default() -> Self {
        Windows {
            volume_pct: Window {
                warn: [65.0, 135.0],
                fail: [55.0, 145.0],
            },
            area_pct: Window {
                warn: [60.0, 160.0],
                fail: [40.0, 200.0],
            },
            height_pct: Window {
                warn: [55.0, 140.0],
                fail: [40.0, 170.0],
            },
            offset_pct: Upper {
                warn: 15.0,
                fail: 25.0,
            },
            shape_pct: Upper {
                warn: 20.0,
                fail: 35.0,
            },
            missing_pct: 10.0,
            bridge_height_pct: 30.0,
            guard_band_k: 2.0,
        }
    }
}

/// Windows for some pads: the fields given replace the default's.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Override {
    /// Component reference (exact), e.g. `U7`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub component: Option<String>,
    /// Pad class (the aperture string of `dpsa pads`), exact.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub aperture: Option<String>,
    /// One pad by name (`U7-3`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pad: Option<String>,
    /// Every component of this package (exact, as the placement file names it); needs
    /// `[components]`. Resolved when the pads are named: the override stands for one copy per
    /// component of the package, in the file's order.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub package: Option<String>,
    /// Replaces [`Windows::volume_pct`] (None: the default's stays).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub volume_pct: Option<Window>,
    /// Replaces [`Windows::area_pct`] (None: the default's stays).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub area_pct: Option<Window>,
    /// Replaces [`Windows::height_pct`] (None: the default's stays).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub height_pct: Option<Window>,
    /// Replaces [`Windows::offset_pct`] (None: the default's stays).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset_pct: Option<Upper>,
    /// Replaces [`Windows::shape_pct`] (None: the default's stays).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shape_pct: Option<Upper>,
}

/// Where the design sits on the conveyor, nominally.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Placement {
    /// The design point that lands at the board corner (the map's `x = 0, y = 0`), mm.
    pub design_origin_mm: Point,
    /// The board turned on the conveyor, degrees counter-clockwise (design to board frame).
    pub orientation_deg: f64,
}

impl Default for Placement {
    fn default() -> Self {
        Placement {
            design_origin_mm: [0.0, 0.0],
            orientation_deg: 0.0,
        }
    }
}

impl Placement {
    /// The nominal design-to-board transform: turn about the design origin, then put the
    /// origin at the board corner.
    pub fn nominal(&self) -> Rigid {
        let a = self.orientation_deg.to_radians();
        let (s, c) = a.sin_cos();
        let [ox, oy] = self.design_origin_mm;
        Rigid {
            rotation_rad: a,
            tx: -(c * ox - s * oy),
            ty: -(s * ox + c * oy),
        }
    }
}

/// The board's fiducials (`[fiducials]`); none listed: registration by the paste pattern.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Fiducials {
    /// Design-frame centres, mm.
    pub points_mm: Vec<Point>,
    /// Diameter of the copper disc, mm.
    pub diameter_mm: f64,
    /// Search radius around the nominal place, mm.
    pub search_mm: f64,
}

impl Default for Fiducials {
    fn default() -> Self {
        Fiducials {
            points_mm: Vec::new(),
            diameter_mm: 1.0,
            search_mm: 1.5,
        }
    }
}

/// How the measurement works (not judging).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Measure {
    /// Paste for area and offset: above this % of the stencil thickness.
    pub area_threshold_pct: f64,
    /// Paste for the shape measure (smears are thin): above this, um.
    pub shape_threshold_um: f64,
    /// Fewest valid pixels in the opening, as a fraction, to judge the pad at all.
    pub min_coverage: f64,
    /// The measurement cell reaches this share of the opening's larger size, plus the wall,
    /// beyond its edge (clamped to `cell_margin_mm`), so that an offset deposit is still
    /// measured whole.
    pub cell_margin_share: f64,
    /// Limits of the cell's reach, mm.
    pub cell_margin_mm: Limits,
    /// Bare board used for the local surface: at least this far from every opening, mm.
    pub surface_guard_mm: f64,
    /// ... and within this of the pad (grown step by step to twice and four times when too
    /// few pixels qualify), mm.
    pub surface_reach_mm: f64,
    /// Width of a deposit's wall, mm: the height is the mean over the opening shrunk by this
    /// (at most a quarter of its size), the shape counts paste beyond the opening grown by it.
    pub wall_mm: f64,
    /// Openings closer than this are checked for bridges, mm.
    pub bridge_reach_mm: f64,
    /// The machine's lateral scatter of a measured point, um: on a slope `g` a pixel's height
    /// scatters by `lateral_sigma_um x g` besides its noise (the walls of deposits). Used
    /// for each pad's stated uncertainty only (`dpsa grr` measures it: `lateral_sigma_um`).
    pub lateral_sigma_um: f64,
    /// The machine's scatter of a row's place along the motion, um (encoder and trigger),
    /// over a cell's width of one camera's pixels: those move together, so a deposit's front
    /// and back walls count it once per row, not per pixel. Used for the stated uncertainty
    /// only (`dpsa grr`: `row_sigma_um`, over segments of 32 columns within a camera).
    pub row_sigma_um: f64,
    /// The correlation of neighbouring rows' shifts (0..1): a deposit's wall spans two or
    /// three rows, which move partly together (`dpsa grr`: `row_correlation`).
    pub row_correlation: f64,
}

impl Default for Measure {
    fn default() -> Self {
        Measure {
            area_threshold_pct: 30.0,
            shape_threshold_um: 10.0,
            min_coverage: 0.85,
            cell_margin_share: 0.5,
            cell_margin_mm: [0.1, 0.8],
            surface_guard_mm: 0.1,
            surface_reach_mm: 0.6,
            wall_mm: 0.06,
            bridge_reach_mm: 0.6,
            lateral_sigma_um: 1.2,
            row_sigma_um: 4.3,
            row_correlation: 0.36,
        }
    }
}

/// The inspection program.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Program {
    /// The program's (recipe's) name, reported as the CFX `RecipeName`; without it the
    /// program file's name stands in.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// The top paste layer (Gerber), relative to the program file.
    pub paste_layer: String,
    /// Stencil thickness, um.
    #[serde(default = "default_stencil")]
    pub stencil_um: f64,
    /// Where the design sits on the conveyor (`[placement]`).
    #[serde(default)]
    pub placement: Placement,
    /// The fiducials (`[fiducials]`).
    #[serde(default)]
    pub fiducials: Fiducials,
    /// How pads are measured (`[measure]`).
    #[serde(default)]
    pub measure: Measure,
    /// How the paste reflects against the board (`[reflectance]`): the board map takes its
    /// bend of the phase out of the deposits' walls (`dpsa_board::places`).
    #[serde(default, skip_serializing_if = "Reflectance::is_zero")]
    pub reflectance: Reflectance,
    /// Every pad's windows unless an override matches (`[windows]`).
    #[serde(default)]
    pub windows: Windows,
    /// Pad names from a pick-and-place file (`dpsa program`): the nearest component and a
    /// pin for every pad the layer does not name itself.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub components: Option<crate::teach::placement::ComponentsFile>,
    /// Windows for some pads (`[[override]]`), first match wins ([`Program::windows_for`]).
    #[serde(default, rename = "override", skip_serializing_if = "Vec::is_empty")]
    pub overrides: Vec<Override>,
    /// Inspect a paste layer whose file has no end (`M02`): it may be cut short, so it is
    /// refused unless this is true (the report then says so).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub allow_truncated_layer: bool,
    /// Simulator only: the recording's print truth (`print.json`), relative to the program.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub truth: Option<String>,
}

fn default_stencil() -> f64 {
    100.0
}

/// How the paste reflects against the board (`[reflectance]`), a constant of the machine
/// (its illumination and optics) and the materials (the paste, the solder mask).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Reflectance {
    /// The paste's background (the fringes' mean level) above the board's, over the board's
    /// fringe contrast, both as the cameras see them: `(B_paste - B_board) / C_board`. With
    /// it the board map takes the paste's reflectance out of the walls' heights (`docs/spc.md`,
    /// "Where the walls' scatter comes from"); 0 (the default): nothing is taken out.
    #[serde(default)]
    pub background_step: f64,
}

impl Reflectance {
    /// Nothing to take out.
    pub fn is_zero(&self) -> bool {
        self.background_step == 0.0
    }
}

fn check_window(key: &str, w: &Window, lo: f64, hi: f64) -> Result<(), ProgramError> {
    let vals = [w.warn[0], w.warn[1], w.fail[0], w.fail[1]];
    if vals.iter().any(|v| !v.is_finite() || *v < lo || *v > hi) {
        return Err(ProgramError::Invalid {
            key: key.into(),
            why: format!("outside {lo}..={hi} or not a number: {w:?}"),
        });
    }
    if !(w.fail[0] <= w.warn[0] && w.warn[0] < w.warn[1] && w.warn[1] <= w.fail[1]) {
        return Err(ProgramError::Invalid {
            key: key.into(),
            why: format!(
                "inverted: need fail[0] <= warn[0] < warn[1] <= fail[1], got warn {:?} fail {:?}",
                w.warn, w.fail
            ),
        });
    }
    Ok(())
}

fn check_upper(key: &str, u: &Upper) -> Result<(), ProgramError> {
    if !(u.warn.is_finite()
        && u.fail.is_finite()
        && 0.0 < u.warn
        && u.warn <= u.fail
        && u.fail <= 1000.0)
    {
        return Err(ProgramError::Invalid {
            key: key.into(),
            why: format!("inverted or out of range: need 0 < warn <= fail <= 1000, got {u:?}"),
        });
    }
    Ok(())
}

fn check_range(key: &str, v: f64, lo: f64, hi: f64) -> Result<(), ProgramError> {
    if !(v.is_finite() && v >= lo && v <= hi) {
        return Err(ProgramError::Invalid {
            key: key.into(),
            why: format!("{v}, not within {lo}..={hi}"),
        });
    }
    Ok(())
}

impl Windows {
    fn validate(&self, at: &str) -> Result<(), ProgramError> {
        check_window(&format!("{at}volume_pct"), &self.volume_pct, 0.0, 1000.0)?;
        check_window(&format!("{at}area_pct"), &self.area_pct, 0.0, 1000.0)?;
        check_window(&format!("{at}height_pct"), &self.height_pct, 0.0, 1000.0)?;
        check_upper(&format!("{at}offset_pct"), &self.offset_pct)?;
        check_upper(&format!("{at}shape_pct"), &self.shape_pct)?;
        check_range(
            &format!("{at}missing_pct"),
            self.missing_pct,
            0.0,
            self.volume_pct.fail[0],
        )?;
        check_range(
            &format!("{at}bridge_height_pct"),
            self.bridge_height_pct,
            5.0,
            200.0,
        )?;
        check_range(&format!("{at}guard_band_k"), self.guard_band_k, 0.0, 5.0)?;
        Ok(())
    }

    /// These windows with an override's fields put in.
    pub fn with(&self, o: &Override) -> Windows {
        let mut w = self.clone();
        if let Some(v) = o.volume_pct {
            w.volume_pct = v;
        }
        if let Some(v) = o.area_pct {
            w.area_pct = v;
        }
        if let Some(v) = o.height_pct {
            w.height_pct = v;
        }
        if let Some(v) = o.offset_pct {
            w.offset_pct = v;
        }
        if let Some(v) = o.shape_pct {
            w.shape_pct = v;
        }
        w
    }
}

impl Program {
    /// A program for `paste_layer` with every default.
    pub fn new(paste_layer: impl Into<String>) -> Program {
        Program {
            name: None,
            paste_layer: paste_layer.into(),
            stencil_um: default_stencil(),
            placement: Placement::default(),
            fiducials: Fiducials::default(),
            measure: Measure::default(),
            reflectance: Reflectance::default(),
            windows: Windows::default(),
            components: None,
            overrides: Vec::new(),
            allow_truncated_layer: false,
            truth: None,
        }
    }

    /// Parses and validates a program's text; `path` only names it in errors.
    pub fn from_toml_str(text: &str, path: &Path) -> Result<Program, ProgramError> {
        let p: Program = toml::from_str(text).map_err(|e| ProgramError::Parse {
            path: path.to_path_buf(),
            cause: e.to_string(),
        })?;
        p.validate()?;
        Ok(p)
    }

    /// Reads (at most [`MAX_PROGRAM_BYTES`]), parses and validates a program file.
    pub fn load(path: &Path) -> Result<Program, ProgramError> {
        let bytes =
            dpsa_formats::files::read_capped(path, MAX_PROGRAM_BYTES, "program").map_err(|e| {
                ProgramError::Read {
                    path: path.to_path_buf(),
                    cause: format!("{e:#}"),
                }
            })?;
        let text = String::from_utf8(bytes).map_err(|_| ProgramError::Parse {
            path: path.to_path_buf(),
            cause: "not UTF-8 text".into(),
        })?;
        Program::from_toml_str(&text, path)
    }

    /// The program as TOML (every key, defaults included); empty if it cannot be written.
    pub fn to_toml_string(&self) -> String {
        toml::to_string(self).unwrap_or_default()
    }

    /// The paste layer's path, resolved against the program's directory.
    pub fn paste_layer_path(&self, program_path: &Path) -> PathBuf {
        resolve(program_path, &self.paste_layer)
    }

    /// The placement file's path (`[components]`), resolved against the program's directory.
    pub fn components_path(&self, program_path: &Path) -> Option<PathBuf> {
        self.components
            .as_ref()
            .map(|c| resolve(program_path, &c.file))
    }

    /// The truth file's path (simulator recordings only).
    pub fn truth_path(&self, program_path: &Path) -> Option<PathBuf> {
        self.truth.as_ref().map(|t| resolve(program_path, t))
    }

    /// Checks every value against its range (windows ordered and within 0..=1000 %, stencil
    /// 20..=500 um, ...); the first one out is the error.
    pub fn validate(&self) -> Result<(), ProgramError> {
        if self.paste_layer.trim().is_empty() {
            return Err(ProgramError::Invalid {
                key: "paste_layer".into(),
                why: "empty".into(),
            });
        }
        check_range("stencil_um", self.stencil_um, 20.0, 500.0)?;
        let o = self.placement.design_origin_mm;
        check_range("placement.design_origin_mm", o[0], -10_000.0, 10_000.0)?;
        check_range("placement.design_origin_mm", o[1], -10_000.0, 10_000.0)?;
        check_range(
            "placement.orientation_deg",
            self.placement.orientation_deg,
            -360.0,
            360.0,
        )?;
        for p in &self.fiducials.points_mm {
            check_range("fiducials.points_mm", p[0], -10_000.0, 10_000.0)?;
            check_range("fiducials.points_mm", p[1], -10_000.0, 10_000.0)?;
        }
        check_range(
            "fiducials.diameter_mm",
            self.fiducials.diameter_mm,
            0.1,
            10.0,
        )?;
        check_range("fiducials.search_mm", self.fiducials.search_mm, 0.1, 20.0)?;
        // Two fiducials closer than a diameter are one mark (or a copy-paste): the search
        // finds the same mark for both, and the registration's rotation and scale rest on the
        // fiducials' spread.
        let pts = &self.fiducials.points_mm;
        for (a, p) in pts.iter().enumerate() {
            for (b, q) in pts.iter().enumerate().skip(a + 1) {
                let d = (p[0] - q[0]).hypot(p[1] - q[1]);
                if d < self.fiducials.diameter_mm {
                    return Err(ProgramError::Invalid {
                        key: "fiducials.points_mm".into(),
                        why: format!(
                            "fiducials {a} and {b} are {d:.3} mm apart ([{}, {}] and [{}, {}]), less than their diameter {} mm: they are the same mark; every fiducial must be a different mark",
                            p[0], p[1], q[0], q[1], self.fiducials.diameter_mm
                        ),
                    });
                }
            }
        }
        let m = &self.measure;
        check_range(
            "measure.area_threshold_pct",
            m.area_threshold_pct,
            1.0,
            90.0,
        )?;
        check_range(
            "measure.shape_threshold_um",
            m.shape_threshold_um,
            1.0,
            500.0,
        )?;
        check_range("measure.min_coverage", m.min_coverage, 0.1, 1.0)?;
        check_range("measure.cell_margin_share", m.cell_margin_share, 0.0, 2.0)?;
        check_range("measure.cell_margin_mm", m.cell_margin_mm[0], 0.0, 5.0)?;
        check_range(
            "measure.cell_margin_mm",
            m.cell_margin_mm[1],
            m.cell_margin_mm[0],
            5.0,
        )?;
        check_range("measure.surface_guard_mm", m.surface_guard_mm, 0.0, 2.0)?;
        check_range("measure.lateral_sigma_um", m.lateral_sigma_um, 0.0, 100.0)?;
        check_range(
            "reflectance.background_step",
            self.reflectance.background_step,
            -10.0,
            10.0,
        )?;
        check_range("measure.row_sigma_um", m.row_sigma_um, 0.0, 100.0)?;
        check_range("measure.row_correlation", m.row_correlation, 0.0, 1.0)?;
        check_range("measure.surface_reach_mm", m.surface_reach_mm, 0.1, 10.0)?;
        check_range("measure.wall_mm", m.wall_mm, 0.0, 1.0)?;
        check_range("measure.bridge_reach_mm", m.bridge_reach_mm, 0.0, 5.0)?;
        self.windows.validate("windows.")?;
        if let Some(c) = &self.components {
            if c.file.trim().is_empty() {
                return Err(ProgramError::Invalid {
                    key: "components.file".into(),
                    why: "empty".into(),
                });
            }
            check_range("components.max_distance_mm", c.max_distance_mm, 0.1, 100.0)?;
            if (c.format == crate::teach::placement::Format::Csv) != c.columns.is_some() {
                return Err(ProgramError::Invalid {
                    key: "components.columns".into(),
                    why: "given for a format other than csv, or missing for csv".into(),
                });
            }
        }
        for (i, o) in self.overrides.iter().enumerate() {
            if o.component.is_none()
                && o.aperture.is_none()
                && o.pad.is_none()
                && o.package.is_none()
            {
                return Err(ProgramError::Invalid {
                    key: format!("override[{i}]"),
                    why: "matching nothing: give component, aperture, pad or package".into(),
                });
            }
            if o.package.is_some() && self.components.is_none() {
                return Err(ProgramError::Invalid {
                    key: format!("override[{i}].package"),
                    why: "given without [components]: packages come from the placement file".into(),
                });
            }
            self.windows.with(o).validate(&format!("override[{i}]."))?;
        }
        Ok(())
    }

    /// Puts in the packages of the components (`[components]`): every override with a
    /// `package` becomes one copy per component of that package (`components`: reference and
    /// package, in the placement file's order), with `component` set; one that also names a
    /// component stays only if that component has the package.
    pub fn resolve_packages(&mut self, components: &[(String, String)]) {
        let mut out = Vec::with_capacity(self.overrides.len());
        for o in self.overrides.drain(..) {
            let Some(pkg) = &o.package else {
                out.push(o);
                continue;
            };
            for (r, p) in components {
                if p == pkg && o.component.as_ref().is_none_or(|c| c == r) {
                    out.push(Override {
                        component: Some(r.clone()),
                        ..o.clone()
                    });
                }
            }
        }
        self.overrides = out;
    }

    /// The windows of a pad: the first override that matches it, else the default. An
    /// override whose `package` was not resolved ([`Program::resolve_packages`]) matches
    /// nothing.
    pub fn windows_for(&self, pad: &dpsa_gerber::pads::Pad) -> Windows {
        for o in &self.overrides {
            if o.package.is_some() && o.component.is_none() {
                continue;
            }
            let hit = o
                .component
                .as_ref()
                .is_none_or(|c| pad.component.as_ref() == Some(c))
                && o.aperture
                    .as_ref()
                    .is_none_or(|a| pad.aperture.as_ref() == Some(a))
                && o.pad.as_ref().is_none_or(|n| &pad.name() == n);
            if hit {
                return self.windows.with(o);
            }
        }
        self.windows.clone()
    }
}

fn resolve(program_path: &Path, rel: &str) -> PathBuf {
    let p = Path::new(rel);
    if p.is_absolute() {
        p.to_path_buf()
    } else {
        program_path
            .parent()
            .unwrap_or_else(|| Path::new("."))
            .join(p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_round_trip_and_validate() {
        let p = Program::new("paste.gbr");
        p.validate().unwrap();
        let text = p.to_toml_string();
        let q = Program::from_toml_str(&text, Path::new("p.toml")).unwrap();
        assert_eq!(p, q);
        // The smallest program is one line.
        let r = Program::from_toml_str("paste_layer = \"a.gbr\"\n", Path::new("p.toml")).unwrap();
        assert_eq!(r.windows, Windows::default());
        // Without `[reflectance]` nothing is taken out of the walls, and a program that has
        // none writes none; one that has a step keeps it.
        assert!(r.reflectance.is_zero() && !text.contains("reflectance"));
        let text = "paste_layer = \"a.gbr\"\n[reflectance]\nbackground_step = 0.62\n";
        let t = Program::from_toml_str(text, Path::new("p.toml")).unwrap();
        assert_eq!(t.reflectance.background_step, 0.62);
        let again = Program::from_toml_str(&t.to_toml_string(), Path::new("p.toml")).unwrap();
        assert_eq!(again, t);
    }

    #[test]
    fn inverted_windows_and_unknown_keys_are_refused() {
        let bad = [
            "paste_layer = \"a\"\n[windows]\nvolume_pct = { warn = [140.0, 60.0], fail = [50.0, 150.0] }\n",
            "paste_layer = \"a\"\n[windows]\nvolume_pct = { warn = [40.0, 140.0], fail = [50.0, 150.0] }\n",
            "paste_layer = \"a\"\n[windows]\noffset_pct = { warn = 30.0, fail = 20.0 }\n",
            "paste_layer = \"a\"\nstencil_um = nan\n",
            "paste_layer = \"a\"\nstencil_um = 1e9\n",
            "paste_layer = \"a\"\nstensil_um = 100.0\n",
            "paste_layer = \"a\"\n[[override]]\nvolume_pct = { warn = [60.0, 140.0], fail = [50.0, 150.0] }\n",
            "paste_layer = \"a\"\n[[override]]\ncomponent = \"U1\"\nvolume_pct = { warn = [160.0, 140.0], fail = [50.0, 150.0] }\n",
            "stencil_um = 100.0\n",
            "paste_layer = \"a\"\n[reflectance]\nbackground_step = nan\n",
            "paste_layer = \"a\"\n[reflectance]\nbackground_step = 11.0\n",
            "paste_layer = \"a\"\n[reflectance]\ncontrast_step = 0.3\n",
        ];
        for text in bad {
            let e = Program::from_toml_str(text, Path::new("p.toml"));
            assert!(e.is_err(), "accepted: {text}");
        }
    }

    #[test]
    fn overrides_match_first() {
        let text = "paste_layer = \"a\"\n[[override]]\ncomponent = \"U1\"\nvolume_pct = { warn = [60.0, 140.0], fail = [40.0, 160.0] }\n";
        let p = Program::from_toml_str(text, Path::new("p.toml")).unwrap();
        let mut pad = dpsa_gerber::pads::Pad {
            index: 0,
            outline: dpsa_gerber::pads::Outline::Circle {
                centre: [0.0, 0.0],
                diameter: 1.0,
            },
            component: Some("U1".into()),
            pin: Some("1".into()),
            aperture: None,
        };
        assert_eq!(p.windows_for(&pad).volume_pct.fail, [40.0, 160.0]);
        pad.component = Some("U2".into());
        assert_eq!(p.windows_for(&pad).volume_pct.fail, [55.0, 145.0]);
    }

    #[test]
    fn nominal_placement_puts_the_origin_at_the_corner() {
        for deg in [0.0, 90.0, 180.0, 270.0, 12.5] {
            let pl = Placement {
                design_origin_mm: [100.0, 50.0],
                orientation_deg: deg,
            };
            let o = pl.nominal().apply([100.0, 50.0]);
            assert!(o[0].abs() < 1e-9 && o[1].abs() < 1e-9);
        }
    }
}
