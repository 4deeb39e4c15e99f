//! `dpsa spc`: statistical process control of the print from the line's store.

use super::out;
use anyhow::{bail, Context, Result};
use dpsa_spc::rules::Rule;
use dpsa_spc::study::{analyse, Metric, Options, ScopeKind, Series};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// The line's store: its SQLite file (DATA/line.sqlite) or a PostgreSQL URL.
    #[arg(long)]
    store: String,
    /// The line whose boards are read.
    #[arg(long, default_value = dpsa_line::store::DEFAULT_LINE)]
    line: String,
    /// The product (default: the newest inspected board's).
    #[arg(long)]
    product: Option<String>,
    /// The inspection program the boards were inspected under: the limits (Cp, Cpk), the
    /// components and the package families. Without it: the pads' stored names, no limits.
    #[arg(long)]
    program: Option<PathBuf>,
    /// The newest this many inspected boards.
    #[arg(long, default_value_t = 100, value_parser = clap::value_parser!(u32).range(2..=100_000))]
    last: u32,
    /// The first this many boards of the study set every chart's centre and limits (phase I;
    /// the later ones are judged against them); 0: every board (retrospective).
    #[arg(long, default_value_t = dpsa_spc::study::DEFAULT_BASELINE as u32)]
    baseline: u32,
    /// The run rules read on every chart: `we` (Western Electric 1-4), `nelson` (1-8),
    /// `all`, or a list such as `WE1,N2,N3`.
    #[arg(long, default_value = "we")]
    rules: String,
    /// The scopes whose charts raise alarms: a list of board, family, component, pad, print,
    /// each on every rule read or, as `SCOPE:RULE+RULE`, on those rules only (the alarm
    /// policy). Default with `--rules we`: `board:WE1+WE2+WE3,family:WE1,print:WE1+WE2`
    /// (docs/spc.md, "Alarm policy": the known changes' delays kept, a quarter of the false
    /// alarms); with other rules `board,family,print`.
    #[arg(long)]
    alarms: Option<String>,
    /// Output directory: the tables (CSV), alarms and charts (SVG, PNG). New, empty or an
    /// earlier `dpsa spc` output (replaced whole).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Components and pads of lowest volume Cpk charted besides those with an alarm.
    #[arg(long, default_value_t = 10)]
    worst: usize,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

const DIR_KIND: dpsa_formats::files::DirKind = dpsa_formats::files::DirKind {
    format: "dpsa-spc",
    noun: "SPC output",
    ours: |_| false,
};

fn rules(text: &str) -> Result<Vec<Rule>> {
    Ok(match text.to_ascii_lowercase().as_str() {
        "we" => Rule::WESTERN_ELECTRIC.to_vec(),
        "nelson" => Rule::NELSON.to_vec(),
        "all" => Rule::ALL.to_vec(),
        list => {
            let mut v = Vec::new();
            for id in list.split(',').map(str::trim).filter(|s| !s.is_empty()) {
                match Rule::from_id(id) {
                    Some(r) if !v.contains(&r) => v.push(r),
                    Some(_) => {}
                    None => {
                        bail!("--rules: {id:?} is no rule (WE1-WE4, N1-N8, or we, nelson, all)")
                    }
                }
            }
            if v.is_empty() {
                bail!("--rules: no rule given");
            }
            v
        }
    })
}

/// The alarm policy with Western Electric's rules (docs/spc.md, "Alarm policy"): on the 40
/// family charts of a board rule 1 only, on the print's placement rules 1 and 2, on the board's
/// five charts rules 1 to 3; WE4 (8 in a row) is read and counted everywhere but raises none.
/// `--alarms`: `SCOPE[:RULE+RULE...],...` (`dpsa_spc::study::parse_policy`).
fn scopes(text: &str, read: &[Rule]) -> Result<(Vec<ScopeKind>, dpsa_spc::study::AlarmPolicy)> {
    dpsa_spc::study::parse_policy(text, read).map_err(|why| anyhow::anyhow!("--alarms: {why}"))
}

fn idx(v: Option<f64>) -> String {
    v.map_or("-".to_owned(), |x| format!("{x:.2}"))
}

fn line(s: &Series) -> String {
    let lim = s.limits.map_or("no limits".to_owned(), |l| {
        format!("limits {} .. {}", idx(l.lsl), idx(l.usl))
    });
    format!(
        "{:<12} n {:>7}  mean {:>8}  sigma {:>7} / {:>7}  Cp {:>5}  Cpk {:>5}  Ppk {:>5}  {lim}{}",
        s.metric.id(),
        s.n,
        idx(s.mean),
        idx(s.sigma_within),
        idx(s.sigma_overall),
        idx(s.cp.p),
        idx(s.cp.k),
        idx(s.pp.k),
        s.note
            .as_ref()
            .map_or(String::new(), |n| format!("  ({n})")),
    )
}

pub fn run(a: Args) -> Result<()> {
    let location = dpsa_line::store::Location::from_arg(&a.store)
        .map_err(anyhow::Error::msg)
        .context("--store")?;
    let read = rules(&a.rules)?;
    let alarms = match &a.alarms {
        Some(t) => t.clone(),
        None if read == Rule::WESTERN_ELECTRIC => dpsa_spc::study::DEFAULT_POLICY.to_owned(),
        None => "board,family,print".to_owned(),
    };
    let (alarm_scopes, alarm_rules) = scopes(&alarms, &read)?;
    let opts = Options {
        rules: read,
        alarm_scopes,
        alarm_rules,
        baseline: (a.baseline > 0).then_some(a.baseline as usize),
        stencil: Default::default(),
    };
    if let Some(o) = &a.out {
        // Refused before the study, not after it.
        dpsa_formats::files::check_output_dir(o, DIR_KIND)?;
        // Nor may it be, hold or lie inside an input (symlinks resolved): the store and the
        // program.
        use dpsa_formats::files::Input;
        let mut inputs: Vec<Input> = a.program.iter().map(|p| Input::File(p)).collect();
        if let dpsa_line::store::Location::Sqlite(s) = &location {
            inputs.push(Input::File(s));
        }
        dpsa_formats::files::refuse_overwrite_dir("--out", o, &inputs)?;
    }
    let src = dpsa_spc::load::Source {
        store: &location,
        line: &a.line,
        product: a.product.as_deref(),
        program: a.program.as_deref(),
        last: a.last as usize,
        read_only: false,
    };
    let loaded = dpsa_spc::load::load(&src)?;
    let report = analyse(&loaded.study, &loaded.product, &opts);
    let loop_cfg = dpsa_line::printer::LoopConfig::default();
    let proposal = dpsa_line::printer::offline_proposal(&report.prints, &loop_cfg);
    let printer_message = proposal.as_ref().map(|p| {
        let stretch = report
            .prints
            .iter()
            .rev()
            .flatten()
            .next()
            .map(|x| x.stretch_ppm);
        dpsa_line::printer::message(
            p,
            &loop_cfg,
            &format!("dpsa/{}", a.line),
            &a.line,
            &loaded.product,
            report.boards.first().map_or("", |b| &b.run_id),
            report.boards.last().map_or("", |b| &b.run_id),
            report.boards.len(),
            stretch,
            &dpsa_inspect::report::iso_now(),
        )
    });
    let written = match &a.out {
        Some(o) => {
            let dir = dpsa_formats::files::OutputDir::create(o, DIR_KIND)?;
            let w = dpsa_spc::output::write(dir.path(), &loaded.study, &report, a.worst)?;
            let summary = serde_json::json!({
                "product": loaded.product,
                "program_hash": loaded.program_hash,
                "with_program": loaded.with_program,
                "boards_other_program": loaded.other_program,
                "boards_pruned": loaded.pruned,
                "report": &report,
            });
            dpsa_formats::files::write_bytes(
                &dir.path().join("spc.json"),
                serde_json::to_string_pretty(&summary)?.as_bytes(),
            )?;
            if let Some(m) = &printer_message {
                dpsa_formats::files::write_bytes(
                    &dir.path().join("printer_correction.json"),
                    serde_json::to_string_pretty(m)?.as_bytes(),
                )?;
            }
            dir.commit()?;
            Some(w)
        }
        None => None,
    };
    let open: Vec<_> = report.alarms.iter().filter(|x| x.open).collect();
    if a.json {
        let mut worst: Vec<&Series> = report
            .pads
            .iter()
            .filter(|s| s.metric == Metric::Volume && s.cp.k.is_some())
            .collect();
        worst.sort_by(|x, y| x.cp.k.unwrap_or(0.0).total_cmp(&y.cp.k.unwrap_or(0.0)));
        worst.truncate(a.worst);
        let v = serde_json::json!({
            "product": loaded.product,
            "line": a.line,
            "program_hash": loaded.program_hash,
            "with_program": loaded.with_program,
            "boards": report.boards.len(),
            "first_run_id": report.boards.first().map(|b| &b.run_id),
            "last_run_id": report.boards.last().map(|b| &b.run_id),
            "boards_other_program": loaded.other_program,
            "boards_pruned": loaded.pruned,
            "rules": report.rules,
            "alarm_policy": alarms,
            "rules_in_control_arl": report
                .rules
                .iter()
                .map(|r| (r.id(), dpsa_spc::arl::in_control_arl(*r)))
                .collect::<std::collections::BTreeMap<_, _>>(),
            "baseline_boards": report.baseline.map(|b| b.min(report.boards.len())),
            "board": report.board,
            "families": report.families,
            "print": report.print,
            "prints": report.prints,
            "printer": printer_message,
            "stencil": report.stencil,
            "alarms": report.alarms,
            "open_alarms": open.len(),
            "worst_pads_by_volume_cpk": worst,
            "written": written,
        });
        out!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    let b = &report.boards;
    out!(
        "{} boards of {} on {} ({} to {}), program {}{}",
        b.len(),
        loaded.product,
        a.line,
        b.first().map_or("", |x| &x.run_id),
        b.last().map_or("", |x| &x.run_id),
        loaded.program_hash,
        if loaded.with_program {
            ""
        } else {
            " (not given: no limits, no families)"
        }
    );
    if loaded.other_program > 0 || loaded.pruned > 0 {
        out!(
            "left out: {} boards inspected under another program, {} whose pads were pruned",
            loaded.other_program,
            loaded.pruned
        );
    }
    out!(
        "board (X-bar/S, the board's pads the subgroup; limits from {}; sigma within / overall):",
        match report.baseline {
            Some(k) if k < b.len() => format!("the first {k} boards"),
            _ => "every board".to_owned(),
        }
    );
    for s in &report.board {
        out!("  {}", line(s));
    }
    match report.prints.last() {
        Some(Some(p)) => out!(
            "print on the newest board: x {:.1} +- {:.1} um, y {:.1} +- {:.1} um, rotation {:.2} +- \
             {:.2} mdeg, stretch {:.0} +- {:.0} ppm ({} pads, {} set aside)",
            p.x_um,
            p.uncertainty[0],
            p.y_um,
            p.uncertainty[1],
            p.rotation_mdeg,
            p.uncertainty[2],
            p.stretch_ppm,
            p.uncertainty[3],
            p.pads,
            p.outliers
        ),
        _ => out!("print offset: none (it needs the program's pad places and measured offsets)"),
    }
    if let Some(p) = &proposal {
        out!(
            "printer correction proposed (as if none was applied during these boards): x {:.1} \
             um, y {:.1} um, theta {:.2} mdeg: {}",
            p.correction.x_um,
            p.correction.y_um,
            p.correction.rotation_mdeg,
            p.reason
        );
    }
    if let Some(c) = &report.stencil {
        out!(
            "stencil: {} ({}; {} fine apertures)",
            if c.recommend {
                "CLEAN"
            } else {
                "no clean needed"
            },
            c.reasons.join("; "),
            c.fine_pads
        );
    }
    let rules: Vec<&str> = report.rules.iter().map(|r| r.id()).collect();
    out!(
        "alarms ({}; {}): {} episodes, {} open",
        rules.join(" "),
        alarms,
        report.alarms.len(),
        open.len()
    );
    for x in open.iter().take(20) {
        let pads: Vec<String> = x.pads.iter().map(|(n, v)| format!("{n} {v:.1}")).collect();
        out!(
            "  {} {} {}: {} ({}) since {}; pads {}",
            x.kind.id(),
            x.name,
            x.metric.id(),
            x.rule,
            x.rule_text,
            x.since_run_id,
            pads.join(", ")
        );
    }
    if let (Some(o), Some(w)) = (&a.out, written) {
        out!(
            "wrote {}: tables, {} values, {} charts (SVG and PNG)",
            o.display(),
            w.values,
            w.charts
        );
    }
    Ok(())
}
