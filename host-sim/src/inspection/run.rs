//! `dpsa inspect`: register, measure, judge, and (for a simulated board) compare with the
//! truth. Files are written by [`super::report`].

use super::map::BoardMap;
use super::measure::{measure_all, PadMeasurement, Placed};
use super::pads::{Pad, Point, Rigid};
use super::program::Program;
use super::register::{register, RegisterError, Registration};
use super::truth::{accuracy, detection, Accuracy, Detection, PadTruth};
use super::verdict::{judge, Call, Class, Level};
use serde::Serialize;
use std::collections::BTreeMap;
use std::time::Instant;

/// What the simulator knows about a board it printed.
pub struct Truth<'a> {
    /// The true design-to-board transform.
    pub transform: Rigid,
    /// The injected defect of each pad (`missing`, `insufficient`, `excess`, `offset`,
    /// `bridge`, `smear`), None for a good print.
    pub defects: Vec<Option<String>>,
    /// The true paste height above the board at a board point, um.
    pub height: &'a (dyn Fn(Point) -> f64 + Sync),
}

/// Everything one inspection found.
pub struct Inspection {
    pub registration: Registration,
    pub measurements: Vec<PadMeasurement>,
    pub calls: Vec<Call>,
    pub truth: Option<TruthReport>,
    pub truth_pads: Option<Vec<PadTruth>>,
    /// Register + measure + judge, s (not reading or writing).
    pub inspect_s: f64,
    /// Of which the registration, s.
    pub register_s: f64,
}

/// Pads of at least this size (both ways) are the accuracy goal's group, mm.
pub const LARGE_MM: f64 = 0.5;

#[derive(Clone, Debug, Serialize)]
pub struct TruthReport {
    /// Pads with openings of at least 0.5 x 0.5 mm, defect-free.
    pub large: Accuracy,
    /// Smaller defect-free pads.
    pub small: Accuracy,
    /// The registration against the true placement: largest miss at a pad, um.
    pub registration_error_um: f64,
}

pub fn inspect(
    map: &BoardMap,
    pads: &[Pad],
    program: &Program,
) -> Result<Inspection, RegisterError> {
    let t0 = Instant::now();
    // Fiducials when the program lists them, else the paste pattern.
    let registration = if program.fiducials.points_mm.is_empty() {
        super::register_paste::register_paste(map, pads, program)?
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
    let measurements = measure_all(map, pads, &placed, &t, program);
    let calls: Vec<Call> = measurements
        .iter()
        .zip(pads)
        .map(|(m, p)| judge(m, &program.windows_for(p)))
        .collect();
    let inspect_s = t0.elapsed().as_secs_f64();
    Ok(Inspection {
        registration,
        measurements,
        calls,
        truth: None,
        truth_pads: None,
        inspect_s,
        register_s,
    })
}

/// Measures the truth of every pad and the inspection's accuracy against it.
pub fn attach_truth(i: &mut Inspection, pads: &[Pad], program: &Program, tr: &Truth) {
    attach_truth_shown(i, pads, program, tr, false)
}

/// [`attach_truth`] with a progress bar over the pads on stderr when `progress`.
pub fn attach_truth_shown(
    i: &mut Inspection,
    pads: &[Pad],
    program: &Program,
    tr: &Truth,
    progress: bool,
) {
    let t = i.registration.transform;
    let placed = Placed::new(pads, &t, &[], 1.0);
    let bar = crate::progress::progress_bar(progress, pads.len() as u64, "truth");
    let tp = super::truth::measure_truth_counted(pads, &tr.transform, program, tr.height, &bar);
    bar.finish_and_clear();
    let good: Vec<usize> = (0..pads.len())
        .filter(|&k| tr.defects.get(k).cloned().flatten().is_none())
        .collect();
    let (large, small): (Vec<usize>, Vec<usize>) = good
        .into_iter()
        .partition(|&k| placed.min_size[k] >= LARGE_MM - 1e-9);
    let mut reg_err: f64 = 0.0;
    for p in pads {
        let c = p.outline.centroid();
        let (a, b) = (t.apply(c), tr.transform.apply(c));
        reg_err = reg_err.max((a[0] - b[0]).hypot(a[1] - b[1]) * 1000.0);
    }
    i.truth = Some(TruthReport {
        large: accuracy(&large, &i.measurements, &tp),
        small: accuracy(&small, &i.measurements, &tp),
        registration_error_um: reg_err,
    });
    i.truth_pads = Some(tp);
}

/// Pad counts and calls.
#[derive(Clone, Debug, Serialize)]
pub struct Counts {
    pub total: usize,
    /// Judged (not "not measurable").
    pub measured: usize,
    pub not_measurable: usize,
}

#[derive(Clone, Debug, Serialize)]
pub struct Calls {
    pub pass: usize,
    pub warn: usize,
    pub fail: usize,
    /// Failures per class.
    pub fail_by_class: BTreeMap<String, usize>,
    pub warn_by_class: BTreeMap<String, usize>,
    /// The board's verdict: `fail` if any pad failed (not measurable included).
    pub board: &'static str,
}

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

/// The detection figures of a simulated board.
pub fn detection_of(i: &Inspection, pads: &[Pad], truth: &Truth) -> Detection {
    detection(pads, &truth.defects, &i.calls)
}

/// The JSON report of `dpsa inspect` (`--json`, `report.json`).
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub board: String,
    pub program: String,
    pub pads: Counts,
    pub calls: Calls,
    pub registration: RegistrationReport,
    /// Simulated boards only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub truth: Option<TruthKeys>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub detection: Option<Detection>,
    pub timing: Timing,
    /// The failed pads, `name: class` (at most 200).
    pub failures: Vec<String>,
    /// What the inspection of this layer must not hide (a layer without its M02 end).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub paste_layer_notes: Vec<String>,
}

#[derive(Clone, Debug, Serialize)]
pub struct RegistrationReport {
    pub method: &'static str,
    pub residual_um: f64,
    pub shift_mm: Point,
    pub rotation_deg: f64,
    pub fiducials: Vec<super::register::FiducialHit>,
    /// Registration by the paste pattern: the pads fitted.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pads_used: Option<usize>,
}

/// `truth.*`: the accuracy goal's group (openings of at least 0.5 x 0.5 mm, defect-free) at
/// the top level, the smaller pads apart.
#[derive(Clone, Debug, Serialize)]
pub struct TruthKeys {
    pub volume_err_pct: Option<super::truth::ErrStats>,
    pub height_err_um: Option<super::truth::ErrStats>,
    pub offset_err_um: Option<super::truth::ErrStats>,
    pub area_err_pct: Option<super::truth::ErrStats>,
    pub small: Accuracy,
    pub registration_error_um: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct Timing {
    /// Register, measure and judge (the map in memory), s.
    pub inspect_s: f64,
    /// Of which the registration, s.
    pub register_s: f64,
    pub load_s: f64,
    /// Reading the print truth and integrating it (simulated boards), s.
    pub truth_s: f64,
    pub write_s: f64,
    /// The whole `dpsa inspect`, s: load + the inspections (`--repeat`) + truth + write and
    /// what lies between them.
    pub total_s: f64,
}

impl Report {
    pub fn build(
        board: &str,
        program: &str,
        i: &Inspection,
        pads: &[Pad],
        truth: Option<&Truth>,
        load_s: f64,
        truth_s: f64,
    ) -> Report {
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
        Report {
            board: board.into(),
            program: program.into(),
            pads: c,
            calls,
            registration: RegistrationReport {
                method: i.registration.method,
                residual_um: i.registration.residual_um,
                shift_mm: i.registration.shift_mm,
                rotation_deg: i.registration.rotation_deg,
                fiducials: i.registration.fiducials.clone(),
                pads_used: i.registration.pads_used,
            },
            truth: i.truth.as_ref().map(|t| TruthKeys {
                volume_err_pct: t.large.volume_err_pct.clone(),
                height_err_um: t.large.height_err_um.clone(),
                offset_err_um: t.large.offset_err_um.clone(),
                area_err_pct: t.large.area_err_pct.clone(),
                small: t.small.clone(),
                registration_error_um: t.registration_error_um,
            }),
            detection: truth.map(|t| detection_of(i, pads, t)),
            timing: Timing {
                inspect_s: i.inspect_s,
                register_s: i.register_s,
                load_s,
                truth_s,
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
        if let Some(t) = &self.truth {
            if let (Some(v), Some(h), Some(o)) =
                (&t.volume_err_pct, &t.height_err_um, &t.offset_err_um)
            {
                s += &format!(
                    "  against the truth (openings >= 0.5 mm, {} pads): volume bias {:+.2} rms {:.2} %, height rms {:.2} um, offset rms {:.1} um\n",
                    v.n, v.bias, v.rms, h.rms, o.rms
                );
            }
            if let Some(v) = &t.small.volume_err_pct {
                s += &format!(
                    "  smaller openings ({} pads): volume bias {:+.2} rms {:.2} %\n",
                    v.n, v.bias, v.rms
                );
            }
        }
        if let Some(d) = &self.detection {
            s += &format!(
                "  defects: {} injected, {} detected, {} missed, {} wrong class; {} false failures on {} good pads ({} next to an injected defect); smears {} of {}\n",
                d.injected, d.detected, d.missed, d.wrong_class, d.false_fail, d.defect_free, d.false_fail_next_to_defect, d.smear_detected, d.smear_injected
            );
        }
        s += &format!(
            "  time: map load {:.2} s, inspect {:.3} s, truth {:.2} s, write {:.2} s; total {:.2} s",
            self.timing.load_s,
            self.timing.inspect_s,
            self.timing.truth_s,
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
) -> anyhow::Result<(Vec<Pad>, Vec<String>)> {
    let layer_path = program.paste_layer_path(program_path);
    let layer = super::gerber::read_file(&layer_path)
        .map_err(|e| anyhow::anyhow!("paste layer {}: {e}", layer_path.display()))?;
    let mut notes = Vec::new();
    if !layer.complete {
        if !program.allow_truncated_layer {
            anyhow::bail!(
                "paste layer {}: the file has no end (M02) and may be truncated; set \
                 allow_truncated_layer = true in {} to inspect the {} pads it has",
                layer_path.display(),
                program_path.display(),
                layer.pads.len()
            );
        }
        notes.push(format!(
            "paste layer {} has no end (M02) and may be truncated: {} pads inspected \
             (allow_truncated_layer = true)",
            layer_path.display(),
            layer.pads.len()
        ));
    }
    if layer.pads.is_empty() {
        anyhow::bail!("paste layer {}: no pads", layer_path.display());
    }
    Ok((layer.pads, notes))
}

/// `dpsa inspect`: reads the map, the program, its paste layer (and, with `use_truth`, the
/// truth the program or `truth` names), inspects (`repeat` times, the fastest reported), and
/// writes the report files into `out`.
pub fn inspect_dir(
    board: &std::path::Path,
    program_path: &std::path::Path,
    truth: Option<&std::path::Path>,
    out: Option<&std::path::Path>,
    repeat: u32,
    use_truth: bool,
) -> anyhow::Result<(Report, Inspection)> {
    inspect_dir_shown(board, program_path, truth, out, repeat, use_truth, false)
}

/// [`inspect_dir`] with progress bars on stderr when `progress` (the truth's pads).
pub fn inspect_dir_shown(
    board: &std::path::Path,
    program_path: &std::path::Path,
    truth: Option<&std::path::Path>,
    out: Option<&std::path::Path>,
    repeat: u32,
    use_truth: bool,
    progress: bool,
) -> anyhow::Result<(Report, Inspection)> {
    let t0 = Instant::now();
    let mut program = Program::load(program_path)?;
    let layer_path = program.paste_layer_path(program_path);
    let components_path = program.components_path(program_path);
    if let Some(dir) = out {
        // Before any work: the output may not be (or hold) an input, and may replace only an
        // earlier inspection output.
        let mut inputs = vec![
            crate::files::Input::Dir(board),
            crate::files::Input::File(program_path),
            crate::files::Input::File(&layer_path),
        ];
        let truth_in = truth
            .map(std::path::Path::to_path_buf)
            .or_else(|| program.truth_path(program_path));
        if let Some(t) = &truth_in {
            inputs.push(crate::files::Input::File(t));
        }
        if let Some(c) = &components_path {
            inputs.push(crate::files::Input::File(c));
        }
        crate::files::refuse_overwrite_dir("--out", dir, &inputs)?;
        super::report::check_destination(dir)?;
    }
    let (mut pads, layer_notes) = paste_layer_pads(&program, program_path)?;
    // Pad names (and package overrides) from the program's placement file, if it has one.
    super::teach::apply_components(&mut program, program_path, &mut pads)?;
    let pads = pads;
    let map = BoardMap::open(board)?;
    let load_s = t0.elapsed().as_secs_f64();
    let truth_path = truth
        .map(std::path::Path::to_path_buf)
        .or_else(|| program.truth_path(program_path))
        .filter(|_| use_truth);
    let t_print = Instant::now();
    let print = match &truth_path {
        Some(p) => {
            let t = super::simulated::PrintTruth::load(p, pads.len())?;
            if let (Some(have), Some(want)) = (t.board_id, map.board_id) {
                if have != want {
                    anyhow::bail!(
                        "the print truth {} is of board {have}, the map {} of board {want}: a truth of another board would judge this board's pads against another print",
                        p.display(),
                        board.display()
                    );
                }
            }
            Some(t)
        }
        None => None,
    };
    let print_s = t_print.elapsed().as_secs_f64();
    let height = |q: Point| print.as_ref().map_or(0.0, |p| p.height(q));
    let truth = print.as_ref().map(|p| Truth {
        transform: p.transform,
        defects: p.defects.clone(),
        height: &height,
    });
    let mut best: Option<Inspection> = None;
    for _ in 0..repeat.max(1) {
        let i = inspect(&map, &pads, &program)?;
        if best.as_ref().is_none_or(|b| i.inspect_s < b.inspect_s) {
            best = Some(i);
        }
    }
    let Some(mut i) = best else {
        anyhow::bail!("no inspection ran");
    };
    let mut truth_s = print_s;
    if let Some(tr) = &truth {
        let t1 = Instant::now();
        attach_truth_shown(&mut i, &pads, &program, tr, progress);
        truth_s += t1.elapsed().as_secs_f64();
    }
    let mut report = Report::build(
        &board.display().to_string(),
        &program_path.display().to_string(),
        &i,
        &pads,
        truth.as_ref(),
        load_s,
        truth_s,
    );
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
        super::report::write(
            dir,
            &map,
            &pads,
            &i,
            &program,
            &value,
            super::report::Names {
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
