//! The print process over a run of boards (`dpsa print-process`): what the printer does to
//! every pad, board after board, written into a line's store as inspected boards, so that
//! `dpsa spc` can be tried on a process whose changes are known.
//!
//! Each board's pads are printed from the program's paste layer and measured as the line
//! stores them; no images are made (the measurement's own scatter is a term of the model,
//! as large as `dpsa grr` finds it). In control, per pad `p` and board `b`:
//!
//! - volume, % of the opening: `100 + bias_p + board_b + e`, with `bias_p` the aperture's
//!   own release (`pad_bias_pct`, fixed for the run), `board_b` the board's paste roll
//!   (`board_volume_pct`) and `e` the pad's print and measurement scatter (`volume_pct`);
//! - height and area, % of the stencil and of the opening: half the volume's departure from
//!   100 plus their own scatter (`height_pct`, `area_pct`);
//! - offset, um: the board's print placement (a shift of `print_offset_um` per axis and a
//!   turn of `print_rotation_mrad` about the pads' centre, drawn per board) plus the pad's
//!   scatter (`offset_um`).
//!
//! Changes (`[[change]]`, any number, each from a board on, boards counted from 0):
//!
//! | kind | keys | effect |
//! | --- | --- | --- |
//! | `step` | `at`, `shift_um = [x, y]`, `turn_mrad` | the stencil misaligned at a change-over: the print moves from board `at` on |
//! | `drift` | `from`, `um_per_board = [x, y]` | the print walks away, a little more each board |
//! | `clogging` | `from`, `pct_per_print`, `fine_area_ratio` (0.8) | apertures whose area ratio (area over wall area at the program's stencil) is under `fine_area_ratio` lose `pct_per_print` of volume per print since the later of `from` and the last clean |
//! | `clean` | `at` | the stencil wiped before board `at`: clogging starts again from nothing |
//! | `viscosity` | `from`, `pct_per_board` | every deposit's volume changes by this per board (the paste drying on the stencil) |
//!
//! Every pad is judged against its windows in the program (`dpsa_inspect::verdict::judge`), so
//! the stored calls are what the line would store for such values.

use crate::{At, Result, SimError};
use dpsa_inspect::measure::PadMeasurement;
use dpsa_inspect::program::Program;
use dpsa_inspect::verdict::{judge, Level};
use dpsa_line::store::{BoardStart, CameraLoss, Location, Outcome, PadRow, Store};
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// In-control variation, standard deviations.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InControl {
    /// Each aperture's own release, fixed for the run, % of the opening volume.
    pub pad_bias_pct: f64,
    /// Each board's common volume (the paste roll), %.
    pub board_volume_pct: f64,
    /// Each pad's volume on each board, %.
    pub volume_pct: f64,
    /// Each pad's height on each board, % of the stencil.
    pub height_pct: f64,
    /// Each pad's area on each board, % of the opening.
    pub area_pct: f64,
    /// Each pad's offset on each board, per axis, um.
    pub offset_um: f64,
    /// Each board's print shift, per axis, um.
    pub print_offset_um: f64,
    /// Each board's print turn, mrad.
    pub print_rotation_mrad: f64,
}

impl Default for InControl {
    fn default() -> Self {
        InControl {
            pad_bias_pct: 3.0,
            board_volume_pct: 1.5,
            volume_pct: 4.0,
            height_pct: 3.0,
            area_pct: 3.0,
            offset_um: 4.0,
            print_offset_um: 5.0,
            print_rotation_mrad: 0.1,
        }
    }
}

/// A change of the process.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Change {
    /// The print moves from board `at` on.
    Step {
        /// First board moved.
        at: usize,
        /// Shift, um.
        #[serde(default)]
        shift_um: [f64; 2],
        /// Turn about the pads' centre, mrad.
        #[serde(default)]
        turn_mrad: f64,
    },
    /// The print walks away from board `from` on.
    Drift {
        /// First board moved.
        from: usize,
        /// Added each board, um.
        um_per_board: [f64; 2],
    },
    /// Fine apertures clog.
    Clogging {
        /// First print that clogs.
        from: usize,
        /// Volume lost per print since the later of `from` and the last clean, %.
        pct_per_print: f64,
        /// Apertures whose area ratio is under this clog.
        #[serde(default = "fine_area_ratio")]
        fine_area_ratio: f64,
    },
    /// The stencil is wiped before board `at`.
    Clean {
        /// First board after the clean.
        at: usize,
    },
    /// Every deposit's volume changes from board `from` on.
    Viscosity {
        /// First board changed.
        from: usize,
        /// Volume change per board, %.
        pct_per_board: f64,
    },
}

fn fine_area_ratio() -> f64 {
    0.8
}

/// A print process (`PROCESS.toml`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProcessSpec {
    /// Boards printed.
    pub boards: usize,
    /// Seed of every random draw.
    #[serde(default)]
    pub seed: u64,
    /// The product name the boards are stored under.
    #[serde(default = "product")]
    pub product: String,
    /// Seconds between boards.
    #[serde(default = "period")]
    pub period_s: f64,
    /// In-control variation.
    #[serde(default)]
    pub in_control: InControl,
    /// Changes.
    #[serde(default, rename = "change")]
    pub changes: Vec<Change>,
}

fn product() -> String {
    "simulated".into()
}

fn period() -> f64 {
    10.0
}

/// What [`print_process`] wrote.
#[derive(Clone, Debug, Serialize)]
pub struct ProcessSummary {
    /// Boards stored.
    pub boards: usize,
    /// Pads per board.
    pub pads: usize,
    /// Apertures a clogging change clogs (area ratio under its `fine_area_ratio`).
    pub fine_pads: usize,
    /// Boards that failed, warned and passed.
    pub fail: usize,
    /// Boards with a warning at worst.
    pub warn: usize,
    /// Boards that passed.
    pub pass: usize,
    /// The store written.
    pub store: String,
}

impl ProcessSpec {
    /// Reads and checks a process file.
    pub fn load(path: &Path) -> Result<ProcessSpec> {
        let bytes = dpsa_formats::files::read_capped(path, 1 << 20, "print process")?;
        let text = String::from_utf8(bytes)
            .map_err(|_| SimError::Refused(format!("{}: not UTF-8 text", path.display())))?;
        let spec: ProcessSpec = toml::from_str(&text)
            .map_err(|e| SimError::Refused(format!("{}: {e}", path.display())))?;
        spec.validate()
            .map_err(|why| SimError::Refused(format!("{}: {why}", path.display())))?;
        Ok(spec)
    }

    /// Checks the ranges; the sentence names the key.
    pub fn validate(&self) -> std::result::Result<(), String> {
        if !(2..=100_000).contains(&self.boards) {
            return Err(format!("boards = {}: need 2 to 100000", self.boards));
        }
        if !(self.period_s.is_finite() && self.period_s > 0.0 && self.period_s <= 86_400.0) {
            return Err(format!("period_s = {}: need 0 to 86400 s", self.period_s));
        }
        let c = &self.in_control;
        for (k, v) in [
            ("pad_bias_pct", c.pad_bias_pct),
            ("board_volume_pct", c.board_volume_pct),
            ("volume_pct", c.volume_pct),
            ("height_pct", c.height_pct),
            ("area_pct", c.area_pct),
            ("offset_um", c.offset_um),
            ("print_offset_um", c.print_offset_um),
            ("print_rotation_mrad", c.print_rotation_mrad),
        ] {
            if !(v.is_finite() && (0.0..=100.0).contains(&v)) {
                return Err(format!("in_control.{k} = {v}: need 0 to 100"));
            }
        }
        let finite = |k: &str, v: f64, lim: f64| {
            if v.is_finite() && v.abs() <= lim {
                Ok(())
            } else {
                Err(format!("change {k} = {v}: need a number within +-{lim}"))
            }
        };
        for ch in &self.changes {
            let at = match ch {
                Change::Step {
                    at,
                    shift_um,
                    turn_mrad,
                } => {
                    finite("shift_um", shift_um[0], 5000.0)?;
                    finite("shift_um", shift_um[1], 5000.0)?;
                    finite("turn_mrad", *turn_mrad, 100.0)?;
                    *at
                }
                Change::Drift { from, um_per_board } => {
                    finite("um_per_board", um_per_board[0], 1000.0)?;
                    finite("um_per_board", um_per_board[1], 1000.0)?;
                    *from
                }
                Change::Clogging {
                    from,
                    pct_per_print,
                    fine_area_ratio,
                } => {
                    finite("pct_per_print", *pct_per_print, 100.0)?;
                    if !(fine_area_ratio.is_finite() && *fine_area_ratio > 0.0) {
                        return Err(format!("change fine_area_ratio = {fine_area_ratio}"));
                    }
                    *from
                }
                Change::Clean { at } => *at,
                Change::Viscosity {
                    from,
                    pct_per_board,
                } => {
                    finite("pct_per_board", *pct_per_board, 100.0)?;
                    *from
                }
            };
            if at >= self.boards {
                return Err(format!(
                    "a change at board {at}: the run has boards 0 to {}",
                    self.boards - 1
                ));
            }
        }
        Ok(())
    }
}

/// An aperture's area ratio: its area over its wall's at a stencil `stencil_um` thick.
/// What the printer does to one board, before any pad's own scatter.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BoardPrint {
    /// The print's shift, um.
    pub shift_um: [f64; 2],
    /// Its turn about the pads' centre, mrad.
    pub turn_mrad: f64,
    /// Every deposit's volume change, %.
    pub volume_pct: f64,
    /// Clogged apertures: (volume lost %, the area ratio under which an aperture loses it).
    pub clog: Vec<(f64, f64)>,
}

impl ProcessSpec {
    /// Every board's print (the images' process: the pads' own scatter is the simulator's),
    /// from the spec's seed.
    pub fn board_prints(&self) -> Vec<BoardPrint> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(self.seed ^ 0x7072_696e_7465_7273);
        (0..self.boards)
            .map(|b| {
                let z: [f64; 4] = std::array::from_fn(|_| StandardNormal.sample(&mut rng));
                self.board_print(b, z)
            })
            .collect()
    }

    /// Board `b`'s print: its in-control placement and common volume from the four standard
    /// normal draws `z` (shift x, shift y, turn, volume), then the changes in force.
    pub fn board_print(&self, b: usize, z: [f64; 4]) -> BoardPrint {
        let c = &self.in_control;
        let mut shift = [c.print_offset_um * z[0], c.print_offset_um * z[1]];
        let mut turn = c.print_rotation_mrad * z[2];
        let mut volume = c.board_volume_pct * z[3];
        let last_clean = self
            .changes
            .iter()
            .filter_map(|ch| match ch {
                Change::Clean { at } if *at <= b => Some(*at),
                _ => None,
            })
            .max();
        let mut clog: Vec<(f64, f64)> = Vec::new();
        for ch in &self.changes {
            match ch {
                Change::Step {
                    at,
                    shift_um,
                    turn_mrad,
                } if b >= *at => {
                    shift[0] += shift_um[0];
                    shift[1] += shift_um[1];
                    turn += turn_mrad;
                }
                Change::Drift { from, um_per_board } if b >= *from => {
                    let k = (b - from + 1) as f64;
                    shift[0] += k * um_per_board[0];
                    shift[1] += k * um_per_board[1];
                }
                Change::Viscosity {
                    from,
                    pct_per_board,
                } if b >= *from => volume += (b - from + 1) as f64 * pct_per_board,
                Change::Clogging {
                    from,
                    pct_per_print,
                    fine_area_ratio,
                } if b >= *from => {
                    let since = last_clean.map_or(*from, |c| c.max(*from));
                    if b >= since {
                        clog.push(((b - since + 1) as f64 * pct_per_print, *fine_area_ratio));
                    }
                }
                _ => {}
            }
        }
        BoardPrint {
            shift_um: shift,
            turn_mrad: turn,
            volume_pct: volume,
            clog,
        }
    }
}

fn area_ratio(outline: &dpsa_gerber::pads::Outline, stencil_um: f64) -> f64 {
    outline.area() / (outline.perimeter() * stencil_um / 1000.0)
}

/// Writes the process's boards, pads of the program at `program_path`, into a new SQLite
/// store at `store` for the line `line` (an existing store is refused: simulated boards never
/// go among measured ones).
pub fn print_process(
    spec: &ProcessSpec,
    program_path: &Path,
    store: &Path,
    line: &str,
) -> Result<ProcessSummary> {
    spec.validate().map_err(SimError::Refused)?;
    if store.exists() {
        return Err(SimError::Refused(format!(
            "{}: exists; the print process writes a new store only (simulated boards never go \
             into a store of measured ones)",
            store.display()
        )));
    }
    let mut program = Program::load(program_path).map_err(dpsa_inspect::InspectError::from)?;
    let (mut pads, _) = dpsa_inspect::run::paste_layer_pads(&program, program_path)?;
    dpsa_inspect::teach::apply_components(&mut program, program_path, &mut pads)
        .map_err(|e| SimError::Refused(format!("{}: {e}", program_path.display())))?;
    let hash = {
        let a = std::fs::read(program_path).at(|| format!("reading {}", program_path.display()))?;
        let layer = program.paste_layer_path(program_path);
        let b = std::fs::read(&layer).at(|| format!("reading {}", layer.display()))?;
        dpsa_line::config::fnv_hex(&[&a, &b])
    };
    let n = pads.len();
    let centres: Vec<[f64; 2]> = pads.iter().map(|p| p.outline.centroid()).collect();
    let centre = [0, 1].map(|k| centres.iter().map(|c| c[k]).sum::<f64>() / n as f64);
    let ratios: Vec<f64> = pads
        .iter()
        .map(|p| area_ratio(&p.outline, program.stencil_um))
        .collect();
    let windows: Vec<_> = pads.iter().map(|p| program.windows_for(p)).collect();
    let min_size: Vec<f64> = pads
        .iter()
        .map(|p| dpsa_inspect::measure::opening_size(&p.outline).0)
        .collect();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(spec.seed);
    let mut normal = || -> f64 { StandardNormal.sample(&mut rng) };
    let c = spec.in_control.clone();
    let bias: Vec<f64> = (0..n).map(|_| c.pad_bias_pct * normal()).collect();
    let mut st = Store::open(&Location::Sqlite(store.to_path_buf()), line)?;
    let fine_pads = spec
        .changes
        .iter()
        .filter_map(|ch| match ch {
            Change::Clogging {
                fine_area_ratio, ..
            } => Some(ratios.iter().filter(|r| **r < *fine_area_ratio).count()),
            _ => None,
        })
        .max()
        .unwrap_or(0);
    let mut summary = ProcessSummary {
        boards: spec.boards,
        pads: n,
        fine_pads,
        fail: 0,
        warn: 0,
        pass: 0,
        store: store.display().to_string(),
    };
    for b in 0..spec.boards {
        let BoardPrint {
            shift_um: shift,
            turn_mrad: turn,
            volume_pct: volume,
            clog,
        } = spec.board_print(b, [normal(), normal(), normal(), normal()]);
        let id = st.begin_board(&BoardStart {
            run_id: 0x5100_0000 + b as u64,
            product: spec.product.clone(),
            program_hash: hash.clone(),
            calibration_hash: "00000000000051e0".into(),
            started_unix_s: 1_700_000_000.0 + spec.period_s * b as f64,
        })?;
        let mut rows = Vec::with_capacity(n);
        let mut worst = Level::Pass;
        for (k, pad) in pads.iter().enumerate() {
            let lost: f64 = clog
                .iter()
                .filter(|(_, r)| ratios[k] < *r)
                .map(|(l, _)| l)
                .sum();
            let v = 100.0 + bias[k] + volume - lost + c.volume_pct * normal();
            let h = 100.0 + 0.5 * (v - 100.0) + c.height_pct * normal();
            let a = 100.0 + 0.5 * (v - 100.0) + c.area_pct * normal();
            let q = [centres[k][0] - centre[0], centres[k][1] - centre[1]];
            // A turn of `turn` mrad moves a point `d` mm away by `turn x d` um.
            let off = [
                shift[0] - turn * q[1] + c.offset_um * normal(),
                shift[1] + turn * q[0] + c.offset_um * normal(),
            ];
            let area = pad.outline.area();
            let m = PadMeasurement {
                coverage: 1.0,
                volume_um3: v / 100.0 * area * program.stencil_um * 1e6,
                volume_pct: v,
                area_mm2: a / 100.0 * area,
                area_pct: a,
                height_um: h / 100.0 * program.stencil_um,
                height_pct: h,
                height_max_um: h / 100.0 * program.stencil_um,
                offset_um: off,
                offset_pct: 100.0 * off[0].abs().max(off[1].abs()) / 1000.0 / min_size[k],
                ..PadMeasurement::new(k, area)
            };
            let call = judge(&m, &windows[k]);
            worst = worst.max(call.level);
            rows.push(PadRow {
                pad: k as u32,
                name: dpsa_inspect::report::cfx_pad(pad),
                level: call.level.name().into(),
                class: call.class.map(|c| c.name().to_string()),
                volume_um3: Some(m.volume_um3),
                volume_pct: Some(v),
                area_mm2: Some(m.area_mm2),
                area_pct: Some(a),
                height_um: Some(m.height_um),
                height_pct: Some(h),
                offset_x_um: Some(off[0]),
                offset_y_um: Some(off[1]),
                coverage: 1.0,
                uncertainty_um3: None,
            });
        }
        match worst {
            Level::Fail => summary.fail += 1,
            Level::Warn => summary.warn += 1,
            Level::Pass => summary.pass += 1,
        }
        let cams: Vec<CameraLoss> = Vec::new();
        st.finish_board(
            id,
            1_700_000_005.0 + spec.period_s * b as f64,
            &cams,
            &Outcome::Inspected {
                verdict: worst.name().into(),
                pads: rows,
            },
        )?;
    }
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(text: &str) -> std::result::Result<ProcessSpec, String> {
        let s: ProcessSpec = toml::from_str(text).map_err(|e| e.to_string())?;
        s.validate()?;
        Ok(s)
    }

    #[test]
    fn bad_processes_are_refused_by_name() {
        assert!(spec("boards = 60\n").is_ok());
        let e = spec("boards = 1\n").unwrap_err();
        assert!(e.contains("boards"), "{e}");
        let e = spec("boards = 60\n[[change]]\nkind = \"step\"\nat = 60\n").unwrap_err();
        assert!(e.contains("board 60"), "{e}");
        let e = spec("boards = 60\n[[change]]\nkind = \"melt\"\nat = 3\n").unwrap_err();
        assert!(e.contains("melt"), "{e}");
        let e = spec("boards = 60\n[in_control]\nvolume_pct = -1.0\n").unwrap_err();
        assert!(e.contains("in_control.volume_pct"), "{e}");
        let e = spec(
            "boards = 60\n[[change]]\nkind = \"drift\"\nfrom = 3\num_per_board = [0.0, nan]\n",
        )
        .unwrap_err();
        assert!(e.contains("um_per_board"), "{e}");
        let e = spec("boards = 60\nwarp = 3\n").unwrap_err();
        assert!(e.contains("warp"), "{e}");
    }
}
