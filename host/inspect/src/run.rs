//! `dpsa inspect`: register, measure, judge, and report. Files are written by
//! [`crate::report`].
//!
//! An inspection can be handed to an [`Evaluate`] (the simulator's comparison with the print it
//! made, in `dpsa-sim`), whose keys and lines the report carries; the production path has none.

use crate::error::InspectError;
use crate::map::BoardMap;
use crate::measure::{measure_all, Instructions, PadMeasurement, Placed};
use crate::noise::NoiseModel;
use crate::print::PrintOffset;
use crate::program::Program;
use crate::register::{register, RegisterError, Registration};
use crate::verdict::{judge, Call, Class, Level};
use dpsa_gerber::pads::{Pad, Point};
use serde::Serialize;
use std::collections::BTreeMap;
use std::time::Instant;

/// Everything one inspection found.
pub struct Inspection {
    /// Where the design lies on the map.
    pub registration: Registration,
    /// The map's pixel noise and its correlation, from its bare board.
    pub noise: NoiseModel,
    /// One per pad, in the layer's order.
    pub measurements: Vec<PadMeasurement>,
    /// One per pad, in the layer's order.
    pub calls: Vec<Call>,
    /// The print's placement on the board from every pad's offset (`None`: fewer than three
    /// pads with an offset).
    pub print: Option<PrintOffset>,
    /// Register + measure + judge, s (not reading or writing).
    pub inspect_s: f64,
    /// Of which the registration, s.
    pub register_s: f64,
}

/// Registers the design on `map` (by the program's fiducials, else by the paste pattern),
/// measures every pad and judges it.
pub fn inspect(
    map: &BoardMap,
    pads: &[Pad],
    program: &Program,
) -> Result<Inspection, RegisterError> {
    let t0 = Instant::now();
    // Fiducials when the program lists them, else the paste pattern.
    let registration = if program.fiducials.points_mm.is_empty() {
        crate::register_paste::register_paste(map, pads, program)?
    } else {
        register(map, program)?
    };
    let register_s = t0.elapsed().as_secs_f64();
    let t = registration.transform;
    let placed = Placed::new(
        pads,
        &t,
        &program.fiducials.points_mm,
        program.fiducials.diameter_mm,
    );
    let noise = NoiseModel::measure(map, &placed, program.measure.surface_guard_mm);
    let measurements = measure_all(
        Instructions::best(),
        map,
        pads,
        &placed,
        &t,
        program,
        &noise,
    );
    let calls: Vec<Call> = measurements
        .iter()
        .zip(pads)
        .map(|(m, p)| judge(m, &program.windows_for(p)))
        .collect();
    let print = crate::print::of_board(pads, &measurements);
    let inspect_s = t0.elapsed().as_secs_f64();
    Ok(Inspection {
        registration,
        noise,
        measurements,
        calls,
        print,
        inspect_s,
        register_s,
    })
}

/// Pad counts and calls.
#[derive(Clone, Debug, Serialize)]
pub struct Counts {
    /// Pads of the layer.
    pub total: usize,
    /// Judged (not "not measurable").
    pub measured: usize,
    /// Pads that could not be measured (counted as failures in [`Calls`]).
    pub not_measurable: usize,
}

/// Pads per verdict.
#[derive(Clone, Debug, Serialize)]
pub struct Calls {
    /// Pads that passed.
    pub pass: usize,
    /// Pads with a warning.
    pub warn: usize,
    /// Pads that failed.
    pub fail: usize,
    /// Failures per class.
    pub fail_by_class: BTreeMap<String, usize>,
    /// Warnings per class.
    pub warn_by_class: BTreeMap<String, usize>,
    /// The board's verdict: `fail` if any pad failed (not measurable included), else `warn`
    /// if any pad has a warning, else `pass`.
    pub board: &'static str,
}

/// The pad counts and calls of an inspection.
pub fn counts(i: &Inspection) -> (Counts, Calls) {
    let nm = i
        .measurements
        .iter()
        .filter(|m| m.unmeasurable.is_some())
        .count();
    let mut fb = BTreeMap::new();
    let mut wb = BTreeMap::new();
    let (mut p, mut w, mut f) = (0, 0, 0);
    for c in &i.calls {
        match c.level {
            Level::Pass => p += 1,
            Level::Warn => {
                w += 1;
                *wb.entry(c.class.map(Class::name).unwrap_or("?").to_string())
                    .or_insert(0) += 1;
            }
            Level::Fail => {
                f += 1;
                *fb.entry(c.class.map(Class::name).unwrap_or("?").to_string())
                    .or_insert(0) += 1;
            }
        }
    }
    (
        Counts {
            total: i.measurements.len(),
            measured: i.measurements.len() - nm,
            not_measurable: nm,
        },
        Calls {
            pass: p,
            warn: w,
            fail: f,
            fail_by_class: fb,
            warn_by_class: wb,
            board: if f > 0 {
                "fail"
            } else if w > 0 {
                "warn"
            } else {
                "pass"
            },
        },
    )
}

/// The JSON report of `dpsa inspect` (`--json`, `report.json`).
#[derive(Clone, Debug, Serialize)]
pub struct InspectionReport {
    /// The board map's directory, as given.
    pub board: String,
    /// The program file, as given.
    pub program: String,
    /// Pad counts.
    pub pads: Counts,
    /// Pads per verdict and the board's.
    pub calls: Calls,
    /// How the design was registered.
    pub registration: RegistrationReport,
    /// The map's pixel noise on its bare board and its correlation between neighbours (what
    /// each pad's stated uncertainty starts from).
    pub noise: NoiseModel,
    /// The print's placement on the board (translation at the pattern's centre, rotation,
    /// stretch, their uncertainties; null when it could not be fitted). Registered by the
    /// paste pattern itself it reads near zero whatever the printer did.
    pub print: Option<PrintOffset>,
    /// An evaluation's keys (the simulator's `truth` and `detection`), in their place.
    #[serde(flatten, skip_serializing_if = "Option::is_none")]
    pub evaluation: Option<Evaluation>,
    /// Where the time went.
    pub timing: Timing,
    /// The failed pads, `name: class` (at most 200).
    pub failures: Vec<String>,
    /// What the inspection of this layer must not hide (a layer without its M02 end).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub paste_layer_notes: Vec<String>,
}

/// The registration as the report gives it ([`Registration`] without the transform).
#[derive(Clone, Debug, Serialize)]
pub struct RegistrationReport {
    /// `fiducials` or `paste pattern`.
    pub method: &'static str,
    /// Rms of the fit's misses, um.
    pub residual_um: f64,
    /// The board's shift from the nominal placement, mm.
    pub shift_mm: Point,
    /// The board's turn from the nominal placement, degrees counter-clockwise.
    pub rotation_deg: f64,
    /// Every fiducial's search (empty for the paste pattern).
    pub fiducials: Vec<crate::register::FiducialHit>,
    /// Registration by the paste pattern: the pads fitted.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pads_used: Option<usize>,
}

/// What an [`Evaluate`] adds to a report: JSON keys (between `registration` and `timing`, in
/// the order given) and summary lines (before the time line, each ending in a newline).
#[derive(Clone, Debug, Default)]
pub struct Evaluation {
    /// The keys and their values, in the order they are written.
    pub keys: Vec<(String, serde_json::Value)>,
    /// The summary's lines.
    pub summary: String,
}

impl Serialize for Evaluation {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let mut m = s.serialize_map(Some(self.keys.len()))?;
        for (k, v) in &self.keys {
            m.serialize_entry(k, v)?;
        }
        m.end()
    }
}

/// A comparison of an inspection with what is known about the board beyond the measurement
/// (the simulator knows the print it made). The production path has none.
pub trait Evaluate {
    /// The files it reads, which an `--out` must not overwrite.
    fn inputs(&self) -> Vec<std::path::PathBuf>;
    /// Its keys and lines for `inspection` of `pads` on `map`; `progress` shows a bar on
    /// stderr. Its error, whatever its type, reaches the caller as
    /// [`InspectError::Evaluation`] with its message and `source()` chain unchanged.
    fn evaluate(
        &mut self,
        map: &BoardMap,
        pads: &[Pad],
        program: &Program,
        inspection: &Inspection,
        progress: bool,
    ) -> Result<Evaluation, Box<dyn std::error::Error + Send + Sync + 'static>>;
}

/// Where an inspection's time went, s (wall clock).
#[derive(Clone, Debug, Serialize)]
pub struct Timing {
    /// Register, measure and judge (the map in memory), s.
    pub inspect_s: f64,
    /// Of which the registration, s.
    pub register_s: f64,
    /// Reading the program, its paste layer and the map, s.
    pub load_s: f64,
    /// The evaluation, s (reading and integrating the print truth of a simulated board; 0
    /// without one).
    #[serde(rename = "truth_s")]
    pub evaluation_s: f64,
    /// Writing the report files (`--out`), s; 0 without.
    pub write_s: f64,
    /// The whole `dpsa inspect`, s: load + the inspections (`--repeat`) + truth + write and
    /// what lies between them.
    pub total_s: f64,
}

impl InspectionReport {
    /// The report of inspection `i` of `pads`, without an evaluation; `board` and `program`
    /// name the inputs, `load_s` is the time reading them took (write and total times 0).
    pub fn build(
        board: &str,
        program: &str,
        i: &Inspection,
        pads: &[Pad],
        load_s: f64,
    ) -> InspectionReport {
        let (c, calls) = counts(i);
        let failures = i
            .calls
            .iter()
            .enumerate()
            .filter(|(_, c)| c.level == Level::Fail)
            .take(200)
            .map(|(k, c)| {
                format!(
                    "{}: {}",
                    pads[k].name(),
                    c.class.map(Class::name).unwrap_or("?")
                )
            })
            .collect();
        InspectionReport {
            board: board.into(),
            program: program.into(),
            pads: c,
            calls,
            noise: i.noise.clone(),
            print: i.print,
            registration: RegistrationReport {
                method: i.registration.method,
                residual_um: i.registration.residual_um,
                shift_mm: i.registration.shift_mm,
                rotation_deg: i.registration.rotation_deg,
                fiducials: i.registration.fiducials.clone(),
                pads_used: i.registration.pads_used,
            },
            evaluation: None,
            timing: Timing {
                inspect_s: i.inspect_s,
                register_s: i.register_s,
                load_s,
                evaluation_s: 0.0,
                write_s: 0.0,
                total_s: 0.0,
            },
            failures,
            paste_layer_notes: Vec::new(),
        }
    }

    /// The terminal summary.
    pub fn summary(&self) -> String {
        let mut s: String = self
            .paste_layer_notes
            .iter()
            .map(|n| format!("WARNING: {n}\n"))
            .collect();
        s += &format!(
            "{} pads, {} measured: {} pass, {} warn, {} fail -> board {}\n",
            self.pads.total,
            self.pads.measured,
            self.calls.pass,
            self.calls.warn,
            self.calls.fail,
            self.calls.board.to_uppercase()
        );
        if !self.calls.fail_by_class.is_empty() {
            let v: Vec<String> = self
                .calls
                .fail_by_class
                .iter()
                .map(|(k, n)| format!("{k} {n}"))
                .collect();
            s += &format!("  failures: {}\n", v.join(", "));
        }
        let by = match self.registration.pads_used {
            Some(n) => format!("paste pattern of {n} pads"),
            None => format!(
                "{} fiducials",
                self.registration
                    .fiducials
                    .iter()
                    .filter(|f| f.found_mm.is_some())
                    .count()
            ),
        };
        s += &format!(
            "  registration: {by}, residual {:.2} um, board shifted ({:.3}, {:.3}) mm, turned {:.3} deg\n",
            self.registration.residual_um,
            self.registration.shift_mm[0],
            self.registration.shift_mm[1],
            self.registration.rotation_deg
        );
        if let Some(e) = &self.evaluation {
            s += &e.summary;
        }
        s += &format!(
            "  time: map load {:.2} s, inspect {:.3} s, truth {:.2} s, write {:.2} s; total {:.2} s",
            self.timing.load_s,
            self.timing.inspect_s,
            self.timing.evaluation_s,
            self.timing.write_s,
            self.timing.total_s
        );
        s
    }
}

/// The pads of a program's paste layer, and what the report must say about the layer. A
/// layer without its end (`M02`) may be cut short: refused unless the program has
/// `allow_truncated_layer = true`, then inspected with a note.
pub fn paste_layer_pads(
    program: &Program,
    program_path: &std::path::Path,
) -> Result<(Vec<Pad>, Vec<String>), InspectError> {
    let layer_path = program.paste_layer_path(program_path);
    let layer = dpsa_gerber::read_file(&layer_path).map_err(|error| InspectError::PasteLayer {
        path: layer_path.clone(),
        error,
    })?;
    let mut notes = Vec::new();
    if !layer.complete {
        if !program.allow_truncated_layer {
            return Err(InspectError::TruncatedLayer {
                path: layer_path,
                program: program_path.to_path_buf(),
                pads: layer.pads.len(),
            });
        }
        notes.push(format!(
            "paste layer {} has no end (M02) and may be truncated: {} pads inspected \
             (allow_truncated_layer = true)",
            layer_path.display(),
            layer.pads.len()
        ));
    }
    if layer.pads.is_empty() {
        return Err(InspectError::NoPads { path: layer_path });
    }
    Ok((layer.pads, notes))
}

/// `dpsa inspect`: reads the map, the program and its paste layer, inspects (`repeat` times,
/// the fastest reported), and writes the report files into `out`.
pub fn inspect_dir(
    board: &std::path::Path,
    program_path: &std::path::Path,
    out: Option<&std::path::Path>,
    repeat: u32,
) -> Result<(InspectionReport, Inspection), InspectError> {
    inspect_dir_with(board, program_path, out, repeat, None, false)
}

/// [`inspect_dir`] with an evaluation whose keys and lines the report carries, and progress
/// bars on stderr when `progress`.
pub fn inspect_dir_with(
    board: &std::path::Path,
    program_path: &std::path::Path,
    out: Option<&std::path::Path>,
    repeat: u32,
    mut evaluate: Option<&mut dyn Evaluate>,
    progress: bool,
) -> Result<(InspectionReport, Inspection), InspectError> {
    let t0 = Instant::now();
    let mut program = Program::load(program_path)?;
    let layer_path = program.paste_layer_path(program_path);
    let components_path = program.components_path(program_path);
    if let Some(dir) = out {
        // Before any work: the output may not be (or hold) an input, and may replace only an
        // earlier inspection output.
        let mut inputs = vec![
            dpsa_formats::files::Input::Dir(board),
            dpsa_formats::files::Input::File(program_path),
            dpsa_formats::files::Input::File(&layer_path),
        ];
        let evaluated = evaluate.as_ref().map(|e| e.inputs()).unwrap_or_default();
        for t in &evaluated {
            inputs.push(dpsa_formats::files::Input::File(t));
        }
        if let Some(c) = &components_path {
            inputs.push(dpsa_formats::files::Input::File(c));
        }
        dpsa_formats::files::refuse_overwrite_dir("--out", dir, &inputs)?;
        crate::report::check_destination(dir)?;
    }
    let (mut pads, layer_notes) = paste_layer_pads(&program, program_path)?;
    // Pad names (and package overrides) from the program's placement file, if it has one.
    crate::teach::apply_components(&mut program, program_path, &mut pads)?;
    let pads = pads;
    let map = BoardMap::open(board)?;
    let load_s = t0.elapsed().as_secs_f64();
    let mut best: Option<Inspection> = None;
    for _ in 0..repeat.max(1) {
        let i = inspect(&map, &pads, &program)?;
        if best.as_ref().is_none_or(|b| i.inspect_s < b.inspect_s) {
            best = Some(i);
        }
    }
    let Some(i) = best else {
        return Err(InspectError::NoInspection);
    };
    let mut report = InspectionReport::build(
        &board.display().to_string(),
        &program_path.display().to_string(),
        &i,
        &pads,
        load_s,
    );
    if let Some(e) = evaluate.as_mut() {
        let t1 = Instant::now();
        report.evaluation = Some(
            e.evaluate(&map, &pads, &program, &i, progress)
                .map_err(InspectError::Evaluation)?,
        );
        report.timing.evaluation_s = t1.elapsed().as_secs_f64();
    }
    report.paste_layer_notes = layer_notes;
    if let Some(dir) = out {
        let t2 = Instant::now();
        let value = serde_json::to_value(&report)?;
        // The board's identity as the map carries it (`board.json`'s `board_id`); a map
        // without one (written before board identities) is named by its directory.
        let unit = map.board_id.map(|id| id.to_string()).unwrap_or_else(|| {
            board
                .file_name()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| "board".into())
        });
        let recipe = program.name.clone().unwrap_or_else(|| {
            program_path
                .file_name()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default()
        });
        // report.json again with the write time, before the directory is swapped in.
        let report_ref = &mut report;
        crate::report::write(
            dir,
            &map,
            &pads,
            &i,
            &program,
            &value,
            crate::report::Names {
                unit: &unit,
                recipe: &recipe,
            },
            move || {
                report_ref.timing.write_s = t2.elapsed().as_secs_f64();
                report_ref.timing.total_s = t0.elapsed().as_secs_f64();
                Ok(serde_json::to_value(&*report_ref)?)
            },
        )?;
    }
    report.timing.total_s = t0.elapsed().as_secs_f64();
    Ok((report, i))
}
