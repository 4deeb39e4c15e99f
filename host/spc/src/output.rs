//! A study's files: tables for spreadsheets, Minitab and JMP, and the charts.
//!
//! - `board.csv`, `families.csv`, `components.csv`, `pads.csv`: one row per scope and measure
//!   with the points, values, mean, sigmas, limits, `Cp/Cpu/Cpl/Cpk`, `Pp/Ppu/Ppl/Ppk` and the
//!   rule firings (`WE1=2 N3=1`);
//! - `boards.csv`: per board (the subgroup of the board charts) its pads' mean and standard
//!   deviation of each measure;
//! - `values.csv`: every value in long form (board, pad, name, component, family, the five
//!   measures), what Minitab's and JMP's own capability and chart dialogs read;
//! - `alarms.csv`: every episode of a rule firing on an alarm chart;
//! - `charts/`: SVG and PNG of the board's charts (every measure), of every family's, and of
//!   the components and pads with an alarm or among the `worst` lowest `Cpk` of volume.

use crate::plot::{draw, Caption, PlotError};
use crate::study::{Metric, Report, ScopeKind, Series, Study};
use std::collections::BTreeSet;
use std::path::Path;

/// Why the files could not be written.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    /// A table.
    #[error("writing {file}: {source}")]
    Csv {
        /// The file.
        file: String,
        /// The cause.
        source: csv::Error,
    },
    /// A chart.
    #[error("chart {file}: {source}")]
    Chart {
        /// The file.
        file: String,
        /// The cause.
        source: PlotError,
    },
    /// The charts' directory.
    #[error("creating {0}: {1}")]
    Dir(String, std::io::Error),
}

fn opt(v: Option<f64>) -> String {
    v.map_or(String::new(), |x| format!("{x}"))
}

fn csv_err(file: &str) -> impl Fn(csv::Error) -> OutputError + '_ {
    move |source| OutputError::Csv {
        file: file.to_owned(),
        source,
    }
}

const SERIES_HEADER: [&str; 25] = [
    "scope",
    "name",
    "pads",
    "measure",
    "points",
    "values",
    "centre",
    "sigma_limits",
    "mean",
    "sigma_within",
    "sigma_overall",
    "lsl",
    "usl",
    "cp",
    "cpu",
    "cpl",
    "cpk",
    "pp",
    "ppu",
    "ppl",
    "ppk",
    "firings",
    "note",
    "limits_shared",
    "rules_read",
];

fn write_series(dir: &Path, file: &str, rows: &[Series], rules: &str) -> Result<(), OutputError> {
    let e = csv_err(file);
    let mut w = csv::Writer::from_path(dir.join(file)).map_err(&e)?;
    w.write_record(SERIES_HEADER).map_err(&e)?;
    for s in rows {
        let l = s.limits.unwrap_or_default();
        let firings: Vec<String> = s.firings.iter().map(|(r, n)| format!("{r}={n}")).collect();
        w.write_record([
            s.kind.id().to_owned(),
            s.name.clone(),
            s.pads.to_string(),
            s.metric.id().to_owned(),
            s.points.to_string(),
            s.n.to_string(),
            opt(s.centre),
            opt(s.sigma_limits),
            opt(s.mean),
            opt(s.sigma_within),
            opt(s.sigma_overall),
            opt(l.lsl),
            opt(l.usl),
            opt(s.cp.p),
            opt(s.cp.upper),
            opt(s.cp.lower),
            opt(s.cp.k),
            opt(s.pp.p),
            opt(s.pp.upper),
            opt(s.pp.lower),
            opt(s.pp.k),
            firings.join(" "),
            s.note.clone().unwrap_or_default(),
            s.limits.is_some().to_string(),
            rules.to_owned(),
        ])
        .map_err(&e)?;
    }
    w.flush().map_err(|io| e(io.into()))?;
    Ok(())
}

/// A file name's part from a scope's name: letters, digits, `.`, `_`, `-` kept, the rest `_`.
fn file_part(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') {
                c
            } else {
                '_'
            }
        })
        .take(80)
        .collect()
}

/// What was written.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Written {
    /// Charts drawn (each as SVG and PNG).
    pub charts: usize,
    /// Rows of `values.csv`.
    pub values: usize,
}

/// Writes the study's files into `dir` (an empty directory being made, see
/// `dpsa_formats::files::OutputDir`). `worst`: how many components and pads of lowest volume
/// `Cpk` get charts besides those with alarms.
pub fn write(
    dir: &Path,
    study: &Study,
    report: &Report,
    worst: usize,
) -> Result<Written, OutputError> {
    let rules: Vec<&str> = report.rules.iter().map(|r| r.id()).collect();
    let rules = rules.join(" ");
    write_series(dir, "board.csv", &report.board, &rules)?;
    write_series(dir, "families.csv", &report.families, &rules)?;
    write_series(dir, "components.csv", &report.components, &rules)?;
    write_series(dir, "pads.csv", &report.pads, &rules)?;
    write_series(dir, "print.csv", &report.print, &rules)?;
    let mut written = Written::default();
    // Per board: the board subgroup's mean and deviation of each measure.
    {
        let file = "boards.csv";
        let e = csv_err(file);
        let mut w = csv::Writer::from_path(dir.join(file)).map_err(&e)?;
        let mut header = vec![
            "board_id".to_owned(),
            "run_id".to_owned(),
            "ended_unix_s".to_owned(),
        ];
        for m in Metric::PAD {
            header.extend([
                format!("{}_n", m.id()),
                format!("{}_mean", m.id()),
                format!("{}_sd", m.id()),
            ]);
        }
        w.write_record(&header).map_err(&e)?;
        let pads = study.pads().len();
        for (b, br) in study.boards().iter().enumerate() {
            let mut rec = vec![
                br.id.to_string(),
                br.run_id.clone(),
                format!("{}", br.ended_unix_s),
            ];
            for m in Metric::PAD {
                let v: Vec<f64> = (0..pads)
                    .map(|p| study.value(m, p, b))
                    .filter(|x| x.is_finite())
                    .collect();
                let n = v.len();
                let mean = (n > 0).then(|| v.iter().sum::<f64>() / n as f64);
                let sd = mean.filter(|_| n >= 2).map(|mu| {
                    (v.iter().map(|x| (x - mu) * (x - mu)).sum::<f64>() / (n - 1) as f64).sqrt()
                });
                rec.extend([n.to_string(), opt(mean), opt(sd)]);
            }
            w.write_record(&rec).map_err(&e)?;
        }
        w.flush().map_err(|io| e(io.into()))?;
    }
    // Every value, long form.
    {
        let file = "values.csv";
        let e = csv_err(file);
        let mut w = csv::Writer::from_path(dir.join(file)).map_err(&e)?;
        let mut header: Vec<&str> =
            vec!["board_id", "run_id", "pad", "name", "component", "family"];
        header.extend(Metric::PAD.map(Metric::id));
        w.write_record(&header).map_err(&e)?;
        for (b, br) in study.boards().iter().enumerate() {
            for (p, spec) in study.pads().iter().enumerate() {
                let vals = Metric::PAD.map(|m| study.value(m, p, b));
                if vals.iter().all(|v| !v.is_finite()) {
                    continue;
                }
                let mut rec = vec![
                    br.id.to_string(),
                    br.run_id.clone(),
                    p.to_string(),
                    spec.name.clone(),
                    spec.component.clone().unwrap_or_default(),
                    spec.family.clone().unwrap_or_default(),
                ];
                rec.extend(vals.map(|v| {
                    if v.is_finite() {
                        format!("{v}")
                    } else {
                        String::new()
                    }
                }));
                w.write_record(&rec).map_err(&e)?;
                written.values += 1;
            }
        }
        w.flush().map_err(|io| e(io.into()))?;
    }
    {
        let file = "print_offsets.csv";
        let e = csv_err(file);
        let mut w = csv::Writer::from_path(dir.join(file)).map_err(&e)?;
        w.write_record([
            "board_id",
            "run_id",
            "x_um",
            "y_um",
            "rotation_mdeg",
            "stretch_ppm",
            "u_x_um",
            "u_y_um",
            "u_rotation_mdeg",
            "u_stretch_ppm",
            "centre_x_mm",
            "centre_y_mm",
            "pads",
            "outliers",
            "scale_um",
        ])
        .map_err(&e)?;
        for (br, p) in study.boards().iter().zip(study.prints()) {
            let mut rec = vec![br.id.to_string(), br.run_id.clone()];
            match p {
                Some(p) => {
                    rec.extend(
                        [p.x_um, p.y_um, p.rotation_mdeg, p.stretch_ppm]
                            .iter()
                            .chain(&p.uncertainty)
                            .chain(&p.centre_mm)
                            .map(|v| format!("{v}")),
                    );
                    rec.extend([
                        p.pads.to_string(),
                        p.outliers.to_string(),
                        format!("{}", p.scale_um),
                    ]);
                }
                None => rec.extend(std::iter::repeat_n(String::new(), 13)),
            }
            w.write_record(&rec).map_err(&e)?;
        }
        w.flush().map_err(|io| e(io.into()))?;
    }
    {
        let file = "alarms.csv";
        let e = csv_err(file);
        let mut w = csv::Writer::from_path(dir.join(file)).map_err(&e)?;
        w.write_record([
            "scope",
            "name",
            "measure",
            "rule",
            "meaning",
            "since_run_id",
            "first_fired_run_id",
            "last_fired_run_id",
            "open",
            "pads_pulling",
        ])
        .map_err(&e)?;
        for a in &report.alarms {
            let pads: Vec<String> = a.pads.iter().map(|(n, v)| format!("{n}={v:.2}")).collect();
            w.write_record([
                a.kind.id(),
                &a.name,
                a.metric.id(),
                a.rule.id(),
                a.rule_text,
                &a.since_run_id,
                &a.first_fired_run_id,
                &a.last_fired_run_id,
                if a.open { "true" } else { "false" },
                &pads.join(" "),
            ])
            .map_err(&e)?;
        }
        w.flush().map_err(|io| e(io.into()))?;
    }
    // Charts: the board and families whole; components and pads with an alarm or among the
    // worst volume Cpk.
    let charts = dir.join("charts");
    std::fs::create_dir_all(&charts)
        .map_err(|io| OutputError::Dir(charts.display().to_string(), io))?;
    let mut wanted: BTreeSet<(ScopeKind, String, Metric)> = BTreeSet::new();
    for s in report
        .board
        .iter()
        .chain(&report.families)
        .chain(&report.print)
    {
        wanted.insert((s.kind, s.name.clone(), s.metric));
    }
    for a in &report.alarms {
        wanted.insert((a.kind, a.name.clone(), a.metric));
    }
    for list in [&report.components, &report.pads] {
        let mut v: Vec<&Series> = list
            .iter()
            .filter(|s| s.metric == Metric::Volume && s.cp.k.is_some())
            .collect();
        v.sort_by(|a, b| a.cp.k.unwrap_or(0.0).total_cmp(&b.cp.k.unwrap_or(0.0)));
        for s in v.into_iter().take(worst) {
            wanted.insert((s.kind, s.name.clone(), s.metric));
        }
    }
    let (first, last) = match (study.boards().first(), study.boards().last()) {
        (Some(a), Some(b)) => (a.run_id.clone(), b.run_id.clone()),
        _ => return Ok(written),
    };
    for (kind, name, m) in wanted {
        let members = study.members(kind, &name);
        let (chart, _, _) = study.chart(kind, &members, m, report.baseline);
        let Ok(chart) = chart else { continue };
        let base = match kind {
            ScopeKind::Print => format!("print-{}", m.id()),
            k => format!("{}-{}-{}", k.id(), file_part(&name), m.id()),
        };
        let scope = match kind {
            ScopeKind::Board => format!("board ({} pads)", members.len()),
            ScopeKind::Pad => format!("pad {name}"),
            ScopeKind::Print => "the print's placement (every pad's offset, robust fit)".to_owned(),
            k => format!("{} {name} ({} pads)", k.id(), members.len()),
        };
        let idx = |i: Option<f64>| i.map_or("-".to_owned(), |v| format!("{v:.2}"));
        let capability = match (chart.cp.p, chart.cp.k) {
            (None, None) => String::new(),
            (p, k) => format!(" · Cp {} · Cpk {}", idx(p), idx(k)),
        };
        let caption = Caption {
            title: format!("{scope} · {}{capability}", m.label()),
            y_label: m.label().to_owned(),
            x_label: format!("{first} to {last}"),
        };
        let svg = charts.join(format!("{base}.svg"));
        let png = charts.join(format!("{base}.png"));
        draw(&chart, &report.rules, &caption, Some(&svg), Some(&png)).map_err(|source| {
            OutputError::Chart {
                file: base.clone(),
                source,
            }
        })?;
        written.charts += 1;
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_names_keep_only_safe_characters() {
        assert_eq!(file_part("R 0.60x0.30"), "R_0.60x0.30");
        assert_eq!(file_part("../../etc"), ".._.._etc");
        assert_eq!(file_part("U7"), "U7");
    }
}
