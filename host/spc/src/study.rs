//! A study: the pads of one program over a run of boards, analysed per pad, component,
//! package family and board, with the alarms the run rules raise.
//!
//! Each pad has one value per board and measure: its I-MR chart ([`crate::chart::individuals`])
//! over the boards that measured it. A group of pads (a component, a package family, every
//! pad of the board) has one subgroup per board, the values of its pads on that board: its
//! X-bar/S chart ([`crate::chart::means_and_deviations`]). The measures are in % of nominal
//! (volume, area, height), so that pads of different sizes share a scale, and in um for the
//! offsets.
//!
//! **Which charts raise alarms.** A board of 6,000 pads has 30,000 pad charts: even the single
//! rule "beyond 3 sigma", right 99.73 % of the time on a process in control, would raise about
//! 80 false alarms a board. Alarms are therefore raised on the charts of the scopes asked for
//! ([`Options::alarm_scopes`]: by default the board and the package families, a few tens of
//! charts), and every chart's firings are counted and reported (`dpsa spc`'s tables) so that
//! a pad or component that keeps firing is seen without paging anyone. An alarm names the
//! pads that pull its chart furthest on the board where it last fired.

use crate::capability::{Indices, SpecLimits};
use crate::chart::{individuals, means_and_deviations, Chart, ChartError, MeanLimits};
use crate::rules::{episodes, fires, Rule};
use crate::stencil::{self, BoardStencil, Cleaning, StencilConfig};
use dpsa_inspect::print::{self, PadOffset, PrintOffset};
use std::collections::BTreeMap;

/// A measure of a pad, or of the print (serialised by its name in tables, [`Metric::id`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Metric {
    /// Volume, % of opening area x stencil thickness.
    Volume,
    /// Mean height, % of the stencil thickness.
    Height,
    /// Area above the paste threshold, % of the opening.
    Area,
    /// Offset of the deposit from the opening along the board's x, um.
    OffsetX,
    /// Along y, um.
    OffsetY,
    /// The print's translation along x at the pattern's centre, um ([`dpsa_inspect::print`]).
    PrintX,
    /// Along y, um.
    PrintY,
    /// The print's rotation, millidegrees.
    PrintRotation,
    /// The print's stretch, ppm.
    PrintStretch,
}

impl Metric {
    /// A pad's measures.
    pub const PAD: [Metric; 5] = [
        Metric::Volume,
        Metric::Height,
        Metric::Area,
        Metric::OffsetX,
        Metric::OffsetY,
    ];

    /// The print's, one value a board.
    pub const PRINT: [Metric; 4] = [
        Metric::PrintX,
        Metric::PrintY,
        Metric::PrintRotation,
        Metric::PrintStretch,
    ];

    /// Its name in tables and files: the store's column.
    pub fn id(self) -> &'static str {
        match self {
            Metric::Volume => "volume_pct",
            Metric::Height => "height_pct",
            Metric::Area => "area_pct",
            Metric::OffsetX => "offset_x_um",
            Metric::OffsetY => "offset_y_um",
            Metric::PrintX => "print_x_um",
            Metric::PrintY => "print_y_um",
            Metric::PrintRotation => "print_rotation_mdeg",
            Metric::PrintStretch => "print_stretch_ppm",
        }
    }

    /// Its axis label.
    pub fn label(self) -> &'static str {
        match self {
            Metric::Volume => "volume, % of nominal",
            Metric::Height => "height, % of stencil",
            Metric::Area => "area, % of opening",
            Metric::OffsetX => "offset x, um",
            Metric::OffsetY => "offset y, um",
            Metric::PrintX => "print x, um",
            Metric::PrintY => "print y, um",
            Metric::PrintRotation => "print rotation, mdeg",
            Metric::PrintStretch => "print stretch, ppm",
        }
    }

    /// Index into [`Metric::PAD`] of a pad's measure; `None` for the print's.
    pub fn pad_index(self) -> Option<usize> {
        Metric::PAD.iter().position(|&m| m == self)
    }
}

impl serde::Serialize for Metric {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.id())
    }
}

/// What a scope is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ScopeKind {
    /// Every pad of the board.
    Board,
    /// A package family's pads.
    Family,
    /// A component's pads.
    Component,
    /// One pad.
    Pad,
    /// The print's placement on the board ([`dpsa_inspect::print`]).
    Print,
}

impl ScopeKind {
    /// Its name.
    pub fn id(self) -> &'static str {
        match self {
            ScopeKind::Board => "board",
            ScopeKind::Family => "family",
            ScopeKind::Component => "component",
            ScopeKind::Pad => "pad",
            ScopeKind::Print => "print",
        }
    }

    /// The kind by name.
    pub fn from_id(id: &str) -> Option<ScopeKind> {
        [
            ScopeKind::Board,
            ScopeKind::Family,
            ScopeKind::Component,
            ScopeKind::Pad,
            ScopeKind::Print,
        ]
        .into_iter()
        .find(|k| k.id() == id)
    }

    /// Its measures.
    pub fn metrics(self) -> &'static [Metric] {
        match self {
            ScopeKind::Print => &Metric::PRINT,
            _ => &Metric::PAD,
        }
    }
}

/// A pad as the study knows it.
#[derive(Clone, Debug, PartialEq)]
pub struct PadSpec {
    /// Its name (`R12-1`).
    pub name: String,
    /// Its component, if known.
    pub component: Option<String>,
    /// Its package family, if known.
    pub family: Option<String>,
    /// Specification limits per measure ([`Metric::pad_index`]).
    pub limits: [SpecLimits; 5],
    /// The opening's centre, design frame, mm (for the print's placement; `None`: unknown).
    pub at_mm: Option<[f64; 2]>,
    /// The aperture's area ratio, area over wall area (for clogging; `None`: unknown).
    pub area_ratio: Option<f64>,
}

/// A board of the study.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct BoardRef {
    /// The store's board id.
    pub id: i64,
    /// Its run id (16 hex digits).
    pub run_id: String,
    /// When it began, Unix seconds.
    pub started_unix_s: f64,
    /// When it ended, Unix seconds.
    pub ended_unix_s: f64,
    /// Its pads judged `bridge` or `shape` (paste under the stencil).
    pub smears: usize,
}

/// The study's data: pads, boards oldest first, and every value.
#[derive(Clone, Debug)]
pub struct Study {
    pads: Vec<PadSpec>,
    boards: Vec<BoardRef>,
    /// `values[m][b * pads + pad]`: NaN where not measured.
    values: [Vec<f64>; 5],
    /// The print's placement on each board (`None`: too few pads with an offset and a place).
    prints: Vec<Option<PrintOffset>>,
    /// Recorded cleans of the stencil, Unix seconds.
    cleans: Vec<f64>,
}

/// Why a study cannot be made.
#[derive(Clone, Debug, PartialEq)]
pub enum StudyError {
    /// A board's values are for another number of pads.
    PadCount {
        /// The board.
        board: i64,
        /// Its pads.
        got: usize,
        /// The program's.
        want: usize,
    },
}

impl std::fmt::Display for StudyError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            StudyError::PadCount { board, got, want } => write!(
                f,
                "board {board} has values for {got} pads, the program has {want}"
            ),
        }
    }
}

impl std::error::Error for StudyError {}

impl Study {
    /// An empty study of `pads`.
    pub fn new(pads: Vec<PadSpec>) -> Study {
        Study {
            pads,
            boards: Vec::new(),
            values: Default::default(),
            prints: Vec::new(),
            cleans: Vec::new(),
        }
    }

    /// Adds a board (after the ones added before): `values[pad][metric]`, `None` or NaN where
    /// not measured. Values are re-laid per pad when the study is analysed.
    pub fn push(&mut self, board: BoardRef, values: &[[Option<f64>; 5]]) -> Result<(), StudyError> {
        if values.len() != self.pads.len() {
            return Err(StudyError::PadCount {
                board: board.id,
                got: values.len(),
                want: self.pads.len(),
            });
        }
        self.boards.push(board);
        for (m, col) in self.values.iter_mut().enumerate() {
            col.extend(
                values
                    .iter()
                    .map(|v| v[m].filter(|x| x.is_finite()).unwrap_or(f64::NAN)),
            );
        }
        let (ox, oy) = (
            Metric::OffsetX.pad_index().unwrap_or(3),
            Metric::OffsetY.pad_index().unwrap_or(4),
        );
        let offsets: Vec<PadOffset> = self
            .pads
            .iter()
            .zip(values)
            .filter_map(|(spec, v)| {
                Some(PadOffset {
                    at_mm: spec.at_mm?,
                    offset_um: [v[ox]?, v[oy]?],
                })
            })
            .collect();
        self.prints.push(print::fit(&offsets));
        Ok(())
    }

    /// The stencil's recorded cleans (Unix seconds): the stencil's assessment counts from the
    /// last.
    pub fn set_cleans(&mut self, cleans: Vec<f64>) {
        self.cleans = cleans;
    }

    /// The print's placement on each board, as the boards.
    pub fn prints(&self) -> &[Option<PrintOffset>] {
        &self.prints
    }

    /// The pads.
    pub fn pads(&self) -> &[PadSpec] {
        &self.pads
    }

    /// The boards, oldest first.
    pub fn boards(&self) -> &[BoardRef] {
        &self.boards
    }

    /// Value of `pad` on board `b` (NaN: not measured); the print's measures are the board's
    /// (`pad` not read).
    pub fn value(&self, m: Metric, pad: usize, b: usize) -> f64 {
        if let Some(k) = m.pad_index() {
            return self.values[k][b * self.pads.len() + pad];
        }
        let Some(Some(p)) = self.prints.get(b) else {
            return f64::NAN;
        };
        match m {
            Metric::PrintX => p.x_um,
            Metric::PrintY => p.y_um,
            Metric::PrintRotation => p.rotation_mdeg,
            _ => p.stretch_ppm,
        }
    }

    /// The pads of a scope, by its kind and name (the board's: every pad).
    pub fn members(&self, kind: ScopeKind, name: &str) -> Vec<usize> {
        (0..self.pads.len())
            .filter(|&p| {
                let s = &self.pads[p];
                match kind {
                    ScopeKind::Board => true,
                    ScopeKind::Family => s.family.as_deref() == Some(name),
                    ScopeKind::Component => s.component.as_deref() == Some(name),
                    ScopeKind::Pad => s.name == name,
                    ScopeKind::Print => false,
                }
            })
            .collect()
    }

    /// The limits the pads `members` share for `m` (`None` when they differ).
    fn shared_limits(&self, members: &[usize], m: Metric) -> Option<SpecLimits> {
        let k = m.pad_index()?;
        let first = self.pads.get(*members.first()?)?.limits[k];
        members
            .iter()
            .all(|&p| self.pads[p].limits[k] == first)
            .then_some(first)
    }

    /// The chart of a scope's measure with its limits from the first `baseline` boards (all
    /// when `None`), and the boards (indices into [`Study::boards`]) of its points.
    pub fn chart(
        &self,
        kind: ScopeKind,
        members: &[usize],
        m: Metric,
        baseline: Option<usize>,
    ) -> (Result<Chart, ChartError>, Vec<usize>, Option<SpecLimits>) {
        let limits = self.shared_limits(members, m);
        let nb = self.boards.len();
        if kind == ScopeKind::Print || (kind == ScopeKind::Pad && members.len() == 1) {
            let p = members.first().copied().unwrap_or(0);
            let (boards, x): (Vec<usize>, Vec<f64>) = (0..nb)
                .map(|b| (b, self.value(m, p, b)))
                .filter(|(_, v)| v.is_finite())
                .unzip();
            let baseline = baseline_points(&boards, baseline);
            return (
                individuals(&x, limits.unwrap_or_default(), baseline),
                boards,
                limits,
            );
        }
        let mut boards = Vec::new();
        let mut groups: Vec<Vec<f64>> = Vec::new();
        for b in 0..nb {
            let g: Vec<f64> = members
                .iter()
                .map(|&p| self.value(m, p, b))
                .filter(|v| v.is_finite())
                .collect();
            if !g.is_empty() {
                boards.push(b);
                groups.push(g);
            }
        }
        let refs: Vec<&[f64]> = groups.iter().map(|g| &g[..]).collect();
        let baseline = baseline_points(&boards, baseline);
        (
            means_and_deviations(
                &refs,
                limits.unwrap_or_default(),
                baseline,
                MeanLimits::Between,
            ),
            boards,
            limits,
        )
    }
}

/// A chart's baseline in its points: those on the first `boards` boards of the study (`None`:
/// all).
fn baseline_points(points: &[usize], boards: Option<usize>) -> Option<usize> {
    boards.map(|k| points.iter().filter(|&&b| b < k).count())
}

/// Per scope, the rules that raise its alarms ([`Options::alarm_rules`]).
pub type AlarmPolicy = Vec<(ScopeKind, Vec<Rule>)>;

/// How to analyse.
#[derive(Clone, Debug)]
pub struct Options {
    /// The rules read on every chart.
    pub rules: Vec<Rule>,
    /// The scopes whose charts raise alarms.
    pub alarm_scopes: Vec<ScopeKind>,
    /// The alarm policy: for a scope listed here, only these rules raise its alarms (the
    /// others are still read and counted); a scope not listed raises on every rule read.
    pub alarm_rules: AlarmPolicy,
    /// The boards (the study's first) every chart's centre and limits come from; `None`: all
    /// (a retrospective study, where a lasting change pulls the centre to itself).
    pub baseline: Option<usize>,
    /// When to recommend cleaning the stencil.
    pub stencil: StencilConfig,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            rules: Rule::WESTERN_ELECTRIC.to_vec(),
            alarm_scopes: vec![ScopeKind::Board, ScopeKind::Family, ScopeKind::Print],
            alarm_rules: Vec::new(),
            baseline: None,
            stencil: StencilConfig::default(),
        }
    }
}

/// Boards whose values set the charts' centres and limits unless told otherwise (`dpsa spc
/// --baseline`): the study's first 25.
pub const DEFAULT_BASELINE: usize = 25;

/// The default alarm policy with Western Electric's rules: chosen on the known process
/// (`docs/spc.md`), the known changes' delays as with every rule, a third of the false alarms.
pub const DEFAULT_POLICY: &str = "board:WE1+WE2+WE3,family:WE1,print:WE1+WE2";

/// An alarm policy's text, `SCOPE[:RULE+RULE...],...`: the scopes that raise alarms, each on
/// every rule of `read` or on the rules given (which must be read); or why it is not one.
pub fn parse_policy(text: &str, read: &[Rule]) -> Result<(Vec<ScopeKind>, AlarmPolicy), String> {
    let mut kinds = Vec::new();
    let mut policy = Vec::new();
    for item in text.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let (scope, rules) = match item.split_once(':') {
            Some((s, r)) => (s.trim(), Some(r)),
            None => (item, None),
        };
        let kind = ScopeKind::from_id(scope).ok_or_else(|| {
            format!("{scope:?} is no scope (board, family, component, pad, print)")
        })?;
        if kinds.contains(&kind) {
            return Err(format!("{scope} given twice"));
        }
        kinds.push(kind);
        if let Some(r) = rules {
            let mut v = Vec::new();
            for id in r.split('+').map(str::trim).filter(|s| !s.is_empty()) {
                match Rule::from_id(id) {
                    Some(rule) if read.contains(&rule) => v.push(rule),
                    Some(_) => return Err(format!("{scope}:{id}: the rule is not read (--rules)")),
                    None => return Err(format!("{scope}:{id:?} is no rule (WE1-WE4, N1-N8)")),
                }
            }
            if v.is_empty() {
                return Err(format!("{scope}: no rule after the colon"));
            }
            policy.push((kind, v));
        }
    }
    Ok((kinds, policy))
}

impl Options {
    /// Western Electric's rules with [`DEFAULT_POLICY`], limits from the first
    /// [`DEFAULT_BASELINE`] boards: what `dpsa spc` and the operator's pages use unless told
    /// otherwise.
    pub fn with_default_policy() -> Options {
        let rules = Rule::WESTERN_ELECTRIC.to_vec();
        let (alarm_scopes, alarm_rules) =
            parse_policy(DEFAULT_POLICY, &rules).unwrap_or_else(|_| (Vec::new(), Vec::new()));
        Options {
            rules,
            alarm_scopes,
            alarm_rules,
            baseline: Some(DEFAULT_BASELINE),
            ..Options::default()
        }
    }

    /// Whether `rule` firing on a chart of `kind` raises an alarm.
    pub fn raises(&self, kind: ScopeKind, rule: Rule) -> bool {
        self.alarm_scopes.contains(&kind)
            && self
                .alarm_rules
                .iter()
                .find(|(k, _)| *k == kind)
                .is_none_or(|(_, r)| r.contains(&rule))
    }
}

/// One chart's summary.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Series {
    /// The scope's kind.
    pub kind: ScopeKind,
    /// Its name (the board's: the product).
    pub name: String,
    /// Pads in it.
    pub pads: usize,
    /// The measure.
    pub metric: Metric,
    /// Points (boards) on its chart.
    pub points: usize,
    /// Values behind them.
    pub n: usize,
    /// Mean of every value.
    pub mean: Option<f64>,
    /// The chart's centre line (its baseline's mean).
    pub centre: Option<f64>,
    /// The sigma its limits are set with (its baseline's within sigma).
    pub sigma_limits: Option<f64>,
    /// Within sigma.
    pub sigma_within: Option<f64>,
    /// Overall sigma.
    pub sigma_overall: Option<f64>,
    /// The limits its pads share (`None`: they differ, or there are none).
    pub limits: Option<SpecLimits>,
    /// `Cp, Cpu, Cpl, Cpk`.
    pub cp: Indices,
    /// `Pp, Ppu, Ppl, Ppk`.
    pub pp: Indices,
    /// Firings per rule (rules that fired at least once).
    pub firings: BTreeMap<Rule, usize>,
    /// Why there is no chart (too few boards, no spread ...).
    pub note: Option<String>,
}

/// An alarm: a rule that fired on a chart, over an episode of boards.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Alarm {
    /// The chart's scope.
    pub kind: ScopeKind,
    /// Its name.
    pub name: String,
    /// The measure.
    pub metric: Metric,
    /// The rule.
    pub rule: Rule,
    /// What the rule means.
    pub rule_text: &'static str,
    /// The first board of the pattern (run id).
    pub since_run_id: String,
    /// The board where the rule first fired.
    pub first_fired_run_id: String,
    /// The last board where it fired.
    pub last_fired_run_id: String,
    /// Whether it still fires on the study's last board.
    pub open: bool,
    /// The pads that pull the chart furthest on the last board it fired on: name and value,
    /// furthest from the chart's centre first (at most five).
    pub pads: Vec<(String, f64)>,
}

/// What a study found.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Report {
    /// The boards, oldest first.
    pub boards: Vec<BoardRef>,
    /// The rules read.
    pub rules: Vec<Rule>,
    /// The boards the limits come from (`None`: all).
    pub baseline: Option<usize>,
    /// The board-wide charts, one per measure.
    pub board: Vec<Series>,
    /// Per package family and measure.
    pub families: Vec<Series>,
    /// Per component and measure.
    pub components: Vec<Series>,
    /// Per pad and measure.
    pub pads: Vec<Series>,
    /// The print's placement: one chart per measure (none without pad places and offsets).
    pub print: Vec<Series>,
    /// The print's placement on each board (as `boards`).
    pub prints: Vec<Option<PrintOffset>>,
    /// Every alarm, oldest episode first.
    pub alarms: Vec<Alarm>,
    /// Whether to clean the stencil, and why (`None`: no aperture's area ratio known).
    pub stencil: Option<Cleaning>,
}

/// The scopes of a study: `(kind, name, members)`, the board first.
pub fn scopes(study: &Study, product: &str) -> Vec<(ScopeKind, String, Vec<usize>)> {
    let mut out = vec![(
        ScopeKind::Board,
        product.to_owned(),
        (0..study.pads.len()).collect(),
    )];
    let mut families: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
    let mut components: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
    for (p, s) in study.pads.iter().enumerate() {
        if let Some(f) = &s.family {
            families.entry(f).or_default().push(p);
        }
        if let Some(c) = &s.component {
            components.entry(c).or_default().push(p);
        }
    }
    out.extend(
        families
            .into_iter()
            .map(|(n, m)| (ScopeKind::Family, n.to_owned(), m)),
    );
    out.extend(
        components
            .into_iter()
            .map(|(n, m)| (ScopeKind::Component, n.to_owned(), m)),
    );
    out.extend(
        study
            .pads
            .iter()
            .enumerate()
            .map(|(p, s)| (ScopeKind::Pad, s.name.clone(), vec![p])),
    );
    if study.prints.iter().any(Option::is_some) {
        out.push((ScopeKind::Print, "print".to_owned(), Vec::new()));
    }
    out
}

/// Analyses `study` (of `product`).
pub fn analyse(study: &Study, product: &str, opts: &Options) -> Report {
    let mut report = Report {
        boards: study.boards.clone(),
        rules: opts.rules.clone(),
        baseline: opts.baseline,
        board: Vec::new(),
        families: Vec::new(),
        components: Vec::new(),
        pads: Vec::new(),
        print: Vec::new(),
        prints: study.prints.clone(),
        alarms: Vec::new(),
        stencil: stencil_of(study, &opts.stencil),
    };
    for (kind, name, members) in scopes(study, product) {
        for &m in kind.metrics() {
            let (chart, boards, limits) = study.chart(kind, &members, m, opts.baseline);
            let mut s = Series {
                kind,
                name: name.clone(),
                pads: members.len(),
                metric: m,
                points: boards.len(),
                n: 0,
                mean: None,
                centre: None,
                sigma_limits: None,
                sigma_within: None,
                sigma_overall: None,
                limits,
                cp: Indices::default(),
                pp: Indices::default(),
                firings: BTreeMap::new(),
                note: None,
            };
            match chart {
                Err(e) => s.note = Some(e.to_string()),
                Ok(c) => {
                    s.n = c.n;
                    s.mean = Some(c.mean);
                    s.centre = Some(c.centre);
                    s.sigma_limits = Some(c.sigma_limits);
                    s.sigma_within = Some(c.sigma_within);
                    s.sigma_overall = c.sigma_overall.is_finite().then_some(c.sigma_overall);
                    s.cp = c.cp;
                    s.pp = c.pp;
                    if c.sigma_limits == 0.0 {
                        s.note = Some("no spread within: no run rule can be read".to_owned());
                    }
                    for &rule in &opts.rules {
                        let at = fires(rule, &c.points, &c.z);
                        if at.is_empty() {
                            continue;
                        }
                        s.firings.insert(rule, at.len());
                        if opts.raises(kind, rule) {
                            for e in episodes(rule, &at) {
                                let last = boards[e.last_fired];
                                report.alarms.push(Alarm {
                                    kind,
                                    name: name.clone(),
                                    metric: m,
                                    rule,
                                    rule_text: rule.text(),
                                    since_run_id: study.boards[boards[e.since]].run_id.clone(),
                                    first_fired_run_id: study.boards[boards[e.first_fired]]
                                        .run_id
                                        .clone(),
                                    last_fired_run_id: study.boards[last].run_id.clone(),
                                    open: e.last_fired + 1 == c.points.len()
                                        && last + 1 == study.boards.len(),
                                    pads: pulling(study, &members, m, last, c.centre),
                                });
                            }
                        }
                    }
                }
            }
            match kind {
                ScopeKind::Board => report.board.push(s),
                ScopeKind::Family => report.families.push(s),
                ScopeKind::Component => report.components.push(s),
                ScopeKind::Pad => report.pads.push(s),
                ScopeKind::Print => report.print.push(s),
            }
        }
    }
    report
}

/// The stencil's assessment from the fine apertures' volumes and the smears of every board.
fn stencil_of(study: &Study, cfg: &StencilConfig) -> Option<Cleaning> {
    if study.pads.iter().all(|p| p.area_ratio.is_none()) {
        return None;
    }
    let fine: Vec<usize> = (0..study.pads.len())
        .filter(|&p| {
            study.pads[p]
                .area_ratio
                .is_some_and(|r| r < cfg.fine_area_ratio)
        })
        .collect();
    let boards: Vec<BoardStencil> = (0..study.boards.len())
        .map(|b| {
            let v: Vec<f64> = fine
                .iter()
                .map(|&p| study.value(Metric::Volume, p, b))
                .filter(|x| x.is_finite())
                .collect();
            BoardStencil {
                fine_volume_pct: (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64),
                smears: study.boards[b].smears,
            }
        })
        .collect();
    // The first board begun after the last recorded clean before the newest board began.
    let recorded = study
        .cleans
        .iter()
        .copied()
        .fold(None, |a: Option<f64>, t| Some(a.map_or(t, |a| a.max(t))));
    let recorded = recorded.map(|t| {
        study
            .boards
            .iter()
            .position(|b| b.started_unix_s > t)
            .unwrap_or(study.boards.len())
    });
    Some(stencil::assess(&boards, fine.len(), cfg, recorded))
}

/// The pads of `members` furthest from `centre` on board `b` (at most five).
fn pulling(
    study: &Study,
    members: &[usize],
    m: Metric,
    b: usize,
    centre: f64,
) -> Vec<(String, f64)> {
    let mut v: Vec<(usize, f64)> = members
        .iter()
        .map(|&p| (p, study.value(m, p, b)))
        .filter(|(_, x)| x.is_finite())
        .collect();
    v.sort_by(|a, b| (b.1 - centre).abs().total_cmp(&(a.1 - centre).abs()));
    v.truncate(5);
    v.into_iter()
        .map(|(p, x)| (study.pads[p].name.clone(), x))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_policy_reads_and_bad_ones_are_refused() {
        let o = Options::with_default_policy();
        assert_eq!(
            o.alarm_scopes,
            [ScopeKind::Board, ScopeKind::Family, ScopeKind::Print]
        );
        assert!(o.raises(ScopeKind::Board, Rule::from_id("WE3").unwrap()));
        assert!(!o.raises(ScopeKind::Family, Rule::from_id("WE2").unwrap()));
        assert!(!o.raises(ScopeKind::Pad, Rule::from_id("WE1").unwrap()));
        let we = &Rule::WESTERN_ELECTRIC;
        for bad in ["shelf", "board,board", "board:N1", "board:XX", "board:"] {
            assert!(parse_policy(bad, we).is_err(), "{bad}");
        }
    }

    fn pad(name: &str, comp: &str, fam: &str) -> PadSpec {
        let l = SpecLimits {
            lsl: Some(55.0),
            usl: Some(145.0),
        };
        PadSpec {
            name: name.to_owned(),
            component: Some(comp.to_owned()),
            family: Some(fam.to_owned()),
            limits: [
                l,
                l,
                l,
                SpecLimits {
                    lsl: Some(-50.0),
                    usl: Some(50.0),
                },
                SpecLimits {
                    lsl: Some(-50.0),
                    usl: Some(50.0),
                },
            ],
            at_mm: None,
            area_ratio: None,
        }
    }

    fn board(i: usize) -> BoardRef {
        BoardRef {
            id: i as i64,
            run_id: format!("{i:016x}"),
            started_unix_s: i as f64 - 0.5,
            ended_unix_s: i as f64,
            smears: 0,
        }
    }

    /// A study whose family `0402` steps down by 10 % at board 30 raises an alarm on that
    /// family's volume, open, naming a pad of it, and none on the family that stayed.
    /// The alarm policy: a scope not asked for raises nothing; one listed with rules raises on
    /// those only; one listed without, on every rule read.
    #[test]
    fn the_alarm_policy_picks_rules_per_scope() {
        let o = Options {
            alarm_scopes: vec![ScopeKind::Board, ScopeKind::Family],
            alarm_rules: vec![(ScopeKind::Family, vec![Rule::We1])],
            ..Options::default()
        };
        assert!(o.raises(ScopeKind::Board, Rule::We4));
        assert!(o.raises(ScopeKind::Family, Rule::We1));
        assert!(!o.raises(ScopeKind::Family, Rule::We2));
        assert!(!o.raises(ScopeKind::Print, Rule::We1));
        assert!(!o.raises(ScopeKind::Pad, Rule::We1));
    }

    #[test]
    fn a_step_in_one_family_raises_its_alarm() {
        let pads = vec![
            pad("R1-1", "R1", "0402"),
            pad("R1-2", "R1", "0402"),
            pad("U1-1", "U1", "QFN"),
            pad("U1-2", "U1", "QFN"),
        ];
        let mut s = Study::new(pads);
        // A fixed, non-random wobble (the test must not depend on a seed).
        let wobble = |b: usize, p: usize| ((b * 7 + p * 3) % 11) as f64 * 0.4 - 2.0;
        for b in 0..40 {
            let step = if b >= 30 { -10.0 } else { 0.0 };
            let vals: Vec<[Option<f64>; 5]> = (0..4)
                .map(|p| {
                    let v = 100.0 + wobble(b, p) + if p < 2 { step } else { 0.0 };
                    [
                        Some(v),
                        Some(100.0 + wobble(b, p)),
                        Some(100.0),
                        Some(wobble(b, p)),
                        None,
                    ]
                })
                .collect();
            s.push(board(b), &vals).unwrap();
        }
        let r = analyse(&s, "demo", &Options::default());
        let fam: Vec<&Alarm> = r
            .alarms
            .iter()
            .filter(|a| a.kind == ScopeKind::Family && a.metric == Metric::Volume)
            .collect();
        assert!(fam.iter().all(|a| a.name == "0402"), "{fam:?}");
        assert!(fam.iter().any(|a| a.open && a.rule == Rule::We1));
        assert!(fam
            .iter()
            .any(|a| a.pads.iter().any(|(n, _)| n.starts_with("R1"))));
        // Area never moved: a note, no chart rules.
        let area = r.board.iter().find(|s| s.metric == Metric::Area).unwrap();
        assert!(area.note.is_some() && area.firings.is_empty());
        // Offset y was never measured.
        let oy = r.pads.iter().find(|s| s.metric == Metric::OffsetY).unwrap();
        assert_eq!(oy.points, 0);
        assert!(oy.note.is_some());
        assert_eq!(r.pads.len(), 4 * 5);
        assert_eq!(r.components.len(), 2 * 5);
    }

    /// 1,000 boards of a process in control (every pad independent, normal): the point rule
    /// fires on the board and family charts (X-bar/S, limits from the first 25 boards) as
    /// often as its in-control run length says, within 4 Poisson sigmas. The pad charts
    /// (I-MR, limits from 25 moving ranges) are counted and stated: their limits' estimation
    /// error makes them fire more than nominal.
    #[test]
    fn in_control_boards_fire_at_the_nominal_rate() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let noise = Normal::new(0.0, 4.0).unwrap();
        let pads: Vec<PadSpec> = (0..60)
            .map(|p| {
                pad(
                    &format!("C{}.{}", p / 2, p % 2),
                    &format!("C{}", p / 2),
                    ["a", "b", "c"][p % 3],
                )
            })
            .collect();
        let mut s = Study::new(pads);
        let boards = 1000;
        for b in 0..boards {
            let vals: Vec<[Option<f64>; 5]> = (0..60)
                .map(|_| [Some(100.0 + noise.sample(&mut rng)), None, None, None, None])
                .collect();
            s.push(board(b), &vals).unwrap();
        }
        let opts = Options {
            rules: vec![Rule::We1],
            alarm_scopes: vec![],
            baseline: Some(25),
            ..Options::default()
        };
        let r = analyse(&s, "p", &opts);
        let count = |v: &[Series]| -> (usize, usize) {
            let c: Vec<&Series> = v.iter().filter(|x| x.metric == Metric::Volume).collect();
            (
                c.len(),
                c.iter()
                    .map(|x| x.firings.get(&Rule::We1).copied().unwrap_or(0))
                    .sum(),
            )
        };
        let arl = crate::arl::in_control_arl(Rule::We1).unwrap();
        let (charts_b, fired_b) = count(&r.board);
        let (charts_f, fired_f) = count(&r.families);
        let charts = (charts_b + charts_f) as f64;
        // Firings in the baseline too (they are judged against limits they helped set): every
        // point counts, at a rate of about 1 / ARL.
        let expected = charts * boards as f64 / arl;
        let fired = (fired_b + fired_f) as f64;
        let (pc, pf) = count(&r.pads);
        eprintln!(
            "in control, {boards} boards: board and family charts fired {fired} times, {expected:.1} \
             expected; pad charts {pf} against {:.1} nominal ({:.2} x)",
            pc as f64 * boards as f64 / arl,
            pf as f64 / (pc as f64 * boards as f64 / arl)
        );
        assert!(
            (fired - expected).abs() < 4.0 * expected.sqrt() + 1.0,
            "{fired} vs {expected}"
        );
    }

    #[test]
    fn a_board_of_the_wrong_pad_count_is_refused() {
        let mut s = Study::new(vec![pad("A-1", "A", "f")]);
        let e = s.push(board(0), &[]).unwrap_err();
        assert!(e.to_string().contains("0 pads"));
    }

    #[test]
    fn mixed_limits_give_no_capability() {
        let mut a = pad("A-1", "A", "f");
        let b = pad("A-2", "A", "f");
        a.limits[0].usl = Some(150.0);
        let mut s = Study::new(vec![a, b]);
        for i in 0..5 {
            let v = [Some(100.0 + i as f64), None, None, None, None];
            s.push(
                board(i),
                &[v, [Some(99.0 - i as f64), None, None, None, None]],
            )
            .unwrap();
        }
        let r = analyse(&s, "p", &Options::default());
        let c = r
            .components
            .iter()
            .find(|s| s.metric == Metric::Volume)
            .unwrap();
        assert_eq!(c.limits, None);
        assert_eq!(c.cp.k, None);
        assert!(c.mean.is_some());
    }
}
