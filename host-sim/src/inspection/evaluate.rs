//! The simulator's side of `dpsa inspect`: a production inspection ([`dpsa_inspect::run`])
//! compared with the print the simulator made (its `print.json`): the accuracy of every
//! measured figure on the defect-free pads and the detection of the injected defects.
//!
//! [`PrintEvaluation`] is the [`Evaluate`] the production run hands its inspection to; the
//! report's `truth` and `detection` keys and the summary's truth lines are its output.

use super::simulated::PrintTruth;
use super::truth::{accuracy, detection, Accuracy, Detection, ErrStats, PadTruth};
use crate::SimError;
use dpsa_gerber::pads::{Pad, Point, Rigid};
use dpsa_inspect::map::BoardMap;
use dpsa_inspect::measure::Placed;
use dpsa_inspect::program::Program;
use dpsa_inspect::run::{Evaluate, Evaluation, Inspection, InspectionReport};
use dpsa_inspect::InspectError;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// What the simulator knows about a board it printed.
pub struct PrintTruthView<'a> {
    /// The true design-to-board transform.
    pub transform: Rigid,
    /// The injected defect of each pad (`missing`, `insufficient`, `excess`, `offset`,
    /// `bridge`, `smear`), None for a good print.
    pub defects: Vec<Option<String>>,
    /// The true paste height above the board at a board point, um.
    pub height: &'a (dyn Fn(Point) -> f64 + Sync),
}

/// Pads of at least this size (both ways) are the accuracy goal's group, mm.
pub const LARGE_MM: f64 = 0.5;

/// The accuracy of one inspection against the truth.
#[derive(Clone, Debug, Serialize)]
pub struct InspectionAccuracy {
    /// Pads with openings of at least 0.5 x 0.5 mm, defect-free.
    pub large: Accuracy,
    /// Smaller defect-free pads.
    pub small: Accuracy,
    /// The registration against the true placement: largest miss at a pad, um.
    pub registration_error_um: f64,
}

/// An inspection against the truth: the accuracy, each pad's true figures, the detection.
pub struct Evaluated {
    /// Accuracy of the measured figures.
    pub report: InspectionAccuracy,
    /// Each pad's true figures, in pad order.
    pub pads: Vec<PadTruth>,
    /// The injected defects found, missed and misnamed, and the false failures.
    pub detection: Detection,
}

/// Measures the truth of every pad and the inspection's accuracy against it.
pub fn evaluate(i: &Inspection, pads: &[Pad], program: &Program, tr: &PrintTruthView) -> Evaluated {
    evaluate_shown(i, pads, program, tr, false)
}

/// [`evaluate`] with a progress bar over the pads on stderr when `progress`.
pub fn evaluate_shown(
    i: &Inspection,
    pads: &[Pad],
    program: &Program,
    tr: &PrintTruthView,
    progress: bool,
) -> Evaluated {
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
    Evaluated {
        report: InspectionAccuracy {
            large: accuracy(&large, &i.measurements, &tp),
            small: accuracy(&small, &i.measurements, &tp),
            registration_error_um: reg_err,
        },
        pads: tp,
        detection: detection(pads, &tr.defects, &i.calls),
    }
}

/// `truth.*`: the accuracy goal's group (openings of at least 0.5 x 0.5 mm, defect-free) at
/// the top level, the smaller pads apart.
#[derive(Clone, Debug, Serialize)]
pub struct AccuracyKeys {
    /// Volume error, % of the true volume.
    pub volume_err_pct: Option<ErrStats>,
    /// Height error, um.
    pub height_err_um: Option<ErrStats>,
    /// Offset error, um.
    pub offset_err_um: Option<ErrStats>,
    /// Area error, % of the true area.
    pub area_err_pct: Option<ErrStats>,
    /// The smaller openings.
    pub small: Accuracy,
    /// The registration against the true placement: largest miss at a pad, um.
    pub registration_error_um: f64,
}

/// The report keys and summary lines of an evaluation.
pub fn evaluation(e: &Evaluated) -> Evaluation {
    let t = &e.report;
    let keys = AccuracyKeys {
        volume_err_pct: t.large.volume_err_pct.clone(),
        height_err_um: t.large.height_err_um.clone(),
        offset_err_um: t.large.offset_err_um.clone(),
        area_err_pct: t.large.area_err_pct.clone(),
        small: t.small.clone(),
        registration_error_um: t.registration_error_um,
    };
    let map = vec![
        (
            "truth".to_string(),
            serde_json::to_value(&keys).unwrap_or_default(),
        ),
        (
            "detection".to_string(),
            serde_json::to_value(&e.detection).unwrap_or_default(),
        ),
    ];
    let mut s = String::new();
    if let (Some(v), Some(h), Some(o)) = (
        &keys.volume_err_pct,
        &keys.height_err_um,
        &keys.offset_err_um,
    ) {
        s += &format!(
            "  against the truth (openings >= 0.5 mm, {} pads): volume bias {:+.2} rms {:.2} %, height rms {:.2} um, offset rms {:.1} um\n",
            v.n, v.bias, v.rms, h.rms, o.rms
        );
    }
    if let Some(v) = &keys.small.volume_err_pct {
        s += &format!(
            "  smaller openings ({} pads): volume bias {:+.2} rms {:.2} %\n",
            v.n, v.bias, v.rms
        );
    }
    let d = &e.detection;
    s += &format!(
        "  defects: {} injected, {} detected, {} missed, {} wrong class; {} false failures on {} good pads ({} next to an injected defect); smears {} of {}\n",
        d.injected, d.detected, d.missed, d.wrong_class, d.false_fail, d.defect_free, d.false_fail_next_to_defect, d.smear_detected, d.smear_injected
    );
    Evaluation {
        keys: map,
        summary: s,
    }
}

/// A report with an evaluation's keys and lines, as `dpsa inspect` writes it for a simulated
/// board.
pub fn with_evaluation(mut r: InspectionReport, e: &Evaluated) -> InspectionReport {
    r.evaluation = Some(evaluation(e));
    r
}

/// The print truth of a simulated board (`print.json`) as an [`Evaluate`]: read when the
/// inspection is done, checked to be of the map's board.
pub struct PrintEvaluation {
    path: PathBuf,
    board: PathBuf,
    /// The last evaluation, for callers that want more than the report's keys.
    pub evaluated: Option<Evaluated>,
}

impl PrintEvaluation {
    /// The truth at `path` for the board map at `board`.
    pub fn new(path: &Path, board: &Path) -> PrintEvaluation {
        PrintEvaluation {
            path: path.to_path_buf(),
            board: board.to_path_buf(),
            evaluated: None,
        }
    }
}

impl Evaluate for PrintEvaluation {
    fn inputs(&self) -> Vec<PathBuf> {
        vec![self.path.clone()]
    }

    fn evaluate(
        &mut self,
        map: &BoardMap,
        pads: &[Pad],
        program: &Program,
        inspection: &Inspection,
        progress: bool,
    ) -> Result<Evaluation, Box<dyn std::error::Error + Send + Sync + 'static>> {
        // The print truth's errors keep their message and chain (`SimError` into the box).
        Ok(self.evaluate_truth(map, pads, program, inspection, progress)?)
    }
}

impl PrintEvaluation {
    fn evaluate_truth(
        &mut self,
        map: &BoardMap,
        pads: &[Pad],
        program: &Program,
        inspection: &Inspection,
        progress: bool,
    ) -> crate::Result<Evaluation> {
        let p = PrintTruth::load(&self.path, pads.len())?;
        if let (Some(have), Some(want)) = (p.board_id, map.board_id) {
            if have != want {
                return Err(SimError::Refused(format!(
                    "the print truth {} is of board {have}, the map {} of board {want}: a truth of another board would judge this board's pads against another print",
                    self.path.display(),
                    self.board.display()
                )));
            }
        }
        let height = |q: Point| p.height(q);
        let truth = PrintTruthView {
            transform: p.transform,
            defects: p.defects.clone(),
            height: &height,
        };
        let e = evaluate_shown(inspection, pads, program, &truth, progress);
        let out = evaluation(&e);
        self.evaluated = Some(e);
        Ok(out)
    }
}

/// `dpsa inspect` on a simulated board: the production run, with the print truth (`truth`, or
/// the one the program names) evaluated when `use_truth`.
pub fn inspect_dir_shown(
    board: &Path,
    program_path: &Path,
    truth: Option<&Path>,
    out: Option<&Path>,
    repeat: u32,
    use_truth: bool,
    progress: bool,
) -> crate::Result<(InspectionReport, Inspection)> {
    let truth_path = match truth {
        Some(t) => Some(t.to_path_buf()),
        None if use_truth => Program::load(program_path)
            .map_err(InspectError::from)?
            .truth_path(program_path),
        None => None,
    };
    let mut eval = truth_path
        .as_deref()
        .filter(|_| use_truth)
        .map(|t| PrintEvaluation::new(t, board));
    Ok(dpsa_inspect::run::inspect_dir_with(
        board,
        program_path,
        out,
        repeat,
        eval.as_mut().map(|e| e as &mut dyn Evaluate),
        progress,
    )?)
}
