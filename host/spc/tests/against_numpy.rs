//! The statistics against an independent implementation: `tests/reference.py`, numpy,
//! written from `tests/REFERENCE.md` alone. Every case (individuals and unequal subgroups,
//! random and built to fire each rule, two-, one- and no-sided limits, no spread, too few
//! points, limits from a baseline of the first points or from all, baselines that cannot be)
//! goes to both; every figure must agree to 1e-9 relative (z and the capability
//! indices relative to the larger of their size and 1, as they cross 0), every rule must fire
//! at the same points, and a case the reference finds undefined must be an error here.
//!
//! The reference runs with `/usr/bin/python3` (Debian's `python3-numpy`, which the test
//! command installs), or the interpreter named by `DPSA_NUMPY_PYTHON`.

use dpsa_spc::capability::{Indices, SpecLimits};
use dpsa_spc::chart::{individuals, means_and_deviations, Chart, MeanLimits};
use dpsa_spc::rules::{fires, Rule};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use serde_json::{json, Value};
use std::io::Write;
use std::process::{Command, Stdio};

enum Case {
    Individuals(Vec<f64>, SpecLimits, Option<usize>),
    Subgroups(Vec<Vec<f64>>, SpecLimits, Option<usize>, MeanLimits),
}

fn limits_json(l: SpecLimits) -> (Value, Value) {
    (json!(l.lsl), json!(l.usl))
}

impl Case {
    fn to_json(&self) -> Value {
        match self {
            Case::Individuals(x, l, b) => {
                let (lsl, usl) = limits_json(*l);
                json!({"kind": "individuals", "x": x, "lsl": lsl, "usl": usl, "baseline": b})
            }
            Case::Subgroups(g, l, b, m) => {
                let (lsl, usl) = limits_json(*l);
                let m = match m {
                    MeanLimits::Within => "within",
                    MeanLimits::Between => "between",
                };
                json!({"kind": "subgroups", "x": g, "lsl": lsl, "usl": usl, "baseline": b,
                       "mean_limits": m})
            }
        }
    }

    fn chart(&self) -> Option<Chart> {
        match self {
            Case::Individuals(x, l, b) => individuals(x, *l, *b).ok(),
            Case::Subgroups(g, l, b, m) => {
                let refs: Vec<&[f64]> = g.iter().map(|v| &v[..]).collect();
                means_and_deviations(&refs, *l, *b, *m).ok()
            }
        }
    }
}

fn cases() -> Vec<Case> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(24);
    let normal = Normal::new(0.0, 1.0).unwrap();
    let mut out = Vec::new();
    let limit_sets = [
        SpecLimits {
            lsl: Some(55.0),
            usl: Some(145.0),
        },
        SpecLimits {
            lsl: None,
            usl: Some(112.0),
        },
        SpecLimits {
            lsl: Some(93.0),
            usl: None,
        },
        SpecLimits::default(),
    ];
    let noise = |n: usize, sd: f64, rng: &mut rand_chacha::ChaCha8Rng| -> Vec<f64> {
        (0..n).map(|_| 100.0 + sd * normal.sample(rng)).collect()
    };
    // Random individuals of many lengths, some with a step, a drift or an outlier.
    for k in 0..60 {
        let n = [2usize, 3, 7, 15, 40, 120, 400][k % 7];
        let mut x = noise(n, 3.0 + (k % 5) as f64, &mut rng);
        match k % 4 {
            1 => x.iter_mut().skip(n / 2).for_each(|v| *v += 6.0),
            2 => x
                .iter_mut()
                .enumerate()
                .for_each(|(i, v)| *v += 0.05 * i as f64),
            3 if n > 3 => x[n / 3] += 25.0,
            _ => {}
        }
        // Every third case sets its limits from its first half (phase I), some with an
        // invalid baseline.
        let baseline = match k % 6 {
            0 => Some((n / 2).max(2)),
            3 => Some(if k % 12 == 3 { 1 } else { n + 1 }),
            _ => None,
        };
        out.push(Case::Individuals(x, limit_sets[k % 4], baseline));
    }
    // Built for the pattern rules: a trend, an alternation, stratification, a mixture.
    let mut trend = noise(40, 2.0, &mut rng);
    for (i, v) in trend.iter_mut().enumerate().skip(20).take(8) {
        *v = 95.0 + 1.7 * i as f64;
    }
    out.push(Case::Individuals(trend, limit_sets[0], Some(20)));
    // Ties: a rise with a flat step is no trend, a repeated value no alternation.
    let ties = vec![
        90.0, 91.0, 92.0, 92.0, 93.0, 94.0, 95.0, 96.0, 101.0, 99.0, 101.0, 99.0, 101.0, 99.0,
        99.0, 101.0, 99.0, 101.0, 99.0, 101.0, 99.0, 101.0, 97.0, 98.5,
    ];
    out.push(Case::Individuals(ties, limit_sets[0], None));
    let alt: Vec<f64> = (0..40)
        .map(|i| 100.0 + if i % 2 == 0 { 2.0 } else { -2.0 } + 0.3 * normal.sample(&mut rng))
        .collect();
    out.push(Case::Individuals(alt, limit_sets[1], None));
    let mut strat = noise(60, 5.0, &mut rng);
    for v in strat.iter_mut().skip(25).take(20) {
        *v = 100.3 + 0.2 * normal.sample(&mut rng);
    }
    out.push(Case::Individuals(strat, limit_sets[2], Some(25)));
    let mix: Vec<f64> = (0..50)
        .map(|i| 100.0 + if (i / 3) % 2 == 0 { 6.0 } else { -6.0 } + normal.sample(&mut rng))
        .collect();
    out.push(Case::Individuals(mix, limit_sets[3], None));
    // Random subgroups of unequal sizes (one of a single value now and then), with shifts.
    for k in 0..40 {
        let groups = [2usize, 3, 10, 30, 80][k % 5];
        let g: Vec<Vec<f64>> = (0..groups)
            .map(|i| {
                let size = if (i + k) % 11 == 3 {
                    1
                } else {
                    2 + (i * 7 + k) % 40
                };
                let shift = if k % 3 == 1 && i > groups / 2 {
                    2.0
                } else {
                    0.0
                };
                noise(size, 4.0, &mut rng)
                    .into_iter()
                    .map(|v| v + shift)
                    .collect()
            })
            .collect();
        let baseline = (k % 3 == 0).then_some((groups / 2).max(2));
        let m = if k % 2 == 0 {
            MeanLimits::Within
        } else {
            MeanLimits::Between
        };
        out.push(Case::Subgroups(g, limit_sets[k % 4], baseline, m));
    }
    // Boards with their own level (a paste roll): limits from the means' moving ranges.
    for k in 0..10 {
        let g: Vec<Vec<f64>> = (0..[5, 25, 60][k % 3])
            .map(|i| {
                let level = 1.5 * normal.sample(&mut rng) + if i > 20 { 3.0 } else { 0.0 };
                noise(50 + 17 * (i % 4), 4.0, &mut rng)
                    .into_iter()
                    .map(|v| v + level)
                    .collect()
            })
            .collect();
        out.push(Case::Subgroups(
            g,
            limit_sets[k % 4],
            (k % 2 == 0).then_some(4),
            MeanLimits::Between,
        ));
    }
    // One subgroup of many values (a whole board's pads), and a long run of boards.
    let big: Vec<Vec<f64>> = (0..25).map(|_| noise(6000, 8.0, &mut rng)).collect();
    out.push(Case::Subgroups(
        big.clone(),
        limit_sets[0],
        Some(10),
        MeanLimits::Within,
    ));
    out.push(Case::Subgroups(
        big,
        limit_sets[0],
        Some(10),
        MeanLimits::Between,
    ));
    // A baseline of subgroups of one value each: no degree of freedom for the limits.
    let mut head: Vec<Vec<f64>> = vec![vec![99.0], vec![101.0], vec![100.5]];
    head.extend((0..5).map(|_| noise(4, 3.0, &mut rng)));
    out.push(Case::Subgroups(
        head,
        limit_sets[0],
        Some(3),
        MeanLimits::Between,
    ));
    // No spread, and too little data: undefined in both.
    out.push(Case::Individuals(vec![100.0; 12], limit_sets[0], None));
    out.push(Case::Individuals(vec![100.0], limit_sets[0], None));
    out.push(Case::Subgroups(
        vec![vec![1.0], vec![2.0], vec![3.0]],
        limit_sets[0],
        None,
        MeanLimits::Within,
    ));
    out.push(Case::Subgroups(
        vec![vec![1.0, 2.0, 4.0]],
        limit_sets[0],
        None,
        MeanLimits::Between,
    ));
    out
}

fn python() -> String {
    std::env::var("DPSA_NUMPY_PYTHON").unwrap_or_else(|_| "/usr/bin/python3".to_owned())
}

fn run_reference(input: &Value) -> Value {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/reference.py");
    let py = python();
    let mut child = Command::new(&py)
        .arg(script)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run {py} (the numpy reference needs Debian's python3-numpy, which tests/run.sh installs): {e}"));
    child
        .stdin
        .take()
        .unwrap()
        .write_all(input.to_string().as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "{py} {script} failed (numpy installed? tests/run.sh installs python3-numpy): {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// `a` and `b` agree to 1e-9 relative to the larger of their sizes and `floor`.
fn close(what: &str, a: Option<f64>, b: &Value, floor: f64) {
    match (a, b.as_f64()) {
        (None, None) => {}
        (Some(a), Some(b)) => {
            let scale = a.abs().max(b.abs()).max(floor);
            assert!(
                (a - b).abs() <= 1e-9 * scale,
                "{what}: {a} here, {b} in numpy"
            );
        }
        (a, _) => panic!("{what}: {a:?} here, {b} in numpy"),
    }
}

fn close_all(what: &str, a: &[Option<f64>], b: &Value, floor: f64) {
    let b = b.as_array().unwrap_or_else(|| panic!("{what}: not a list"));
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        close(&format!("{what}[{i}]"), *x, y, floor);
    }
}

fn indices(what: &str, got: &Indices, r: &Value, names: [&str; 4]) {
    close(&format!("{what} {}", names[0]), got.p, &r[names[0]], 1.0);
    close(
        &format!("{what} {}", names[1]),
        got.upper,
        &r[names[1]],
        1.0,
    );
    close(
        &format!("{what} {}", names[2]),
        got.lower,
        &r[names[2]],
        1.0,
    );
    close(&format!("{what} {}", names[3]), got.k, &r[names[3]], 1.0);
}

#[test]
fn the_statistics_agree_with_the_numpy_reference() {
    let cases = cases();
    let input = json!({"cases": cases.iter().map(Case::to_json).collect::<Vec<_>>()});
    let out = run_reference(&input);
    let results = out["results"].as_array().unwrap();
    assert_eq!(results.len(), cases.len());
    let mut fired: std::collections::BTreeMap<Rule, usize> = Default::default();
    for (k, (case, r)) in cases.iter().zip(results).enumerate() {
        let what = format!("case {k}");
        let Some(c) = case.chart() else {
            // Too few points (or no degree of freedom): undefined in both.
            assert!(
                r["mean"].is_null(),
                "{what}: an error here, a mean in numpy: {r}"
            );
            continue;
        };
        close(&format!("{what} mean"), Some(c.mean), &r["mean"], 0.0);
        close(&format!("{what} centre"), Some(c.centre), &r["centre"], 0.0);
        close(
            &format!("{what} sigma_limits"),
            Some(c.sigma_limits),
            &r["sigma_limits"],
            0.0,
        );
        close(
            &format!("{what} sigma_within"),
            Some(c.sigma_within),
            &r["sigma_within"],
            0.0,
        );
        close(
            &format!("{what} sigma_overall"),
            Some(c.sigma_overall),
            &r["sigma_overall"],
            0.0,
        );
        indices(&what, &c.cp, r, ["cp", "cpu", "cpl", "cpk"]);
        indices(&what, &c.pp, r, ["pp", "ppu", "ppl", "ppk"]);
        let some = |v: &[f64]| v.iter().map(|&x| Some(x)).collect::<Vec<_>>();
        close_all(&format!("{what} lcl"), &some(&c.lcl), &r["lcl"], 0.0);
        close_all(&format!("{what} ucl"), &some(&c.ucl), &r["ucl"], 0.0);
        close_all(&format!("{what} z"), &c.z, &r["z"], 1.0);
        let d = &r["dispersion"];
        close_all(
            &format!("{what} dispersion centre"),
            &c.dispersion.centre,
            &d["centre"],
            0.0,
        );
        close_all(
            &format!("{what} dispersion lcl"),
            &c.dispersion.lcl,
            &d["lcl"],
            1e-12,
        );
        close_all(
            &format!("{what} dispersion ucl"),
            &c.dispersion.ucl,
            &d["ucl"],
            0.0,
        );
        for rule in Rule::ALL {
            let here = fires(rule, &c.points, &c.z);
            let there: Vec<usize> = r["rules"][rule.id()]
                .as_array()
                .unwrap_or_else(|| panic!("{what}: no {rule} in numpy"))
                .iter()
                .map(|v| v.as_u64().unwrap() as usize)
                .collect();
            assert_eq!(here, there, "{what} {rule}");
            *fired.entry(rule).or_default() += here.len();
        }
    }
    // The cases exercise every rule (a comparison of empty lists proves nothing).
    for rule in Rule::ALL {
        assert!(
            fired.get(&rule).copied().unwrap_or(0) > 0,
            "{rule} never fired: {fired:?}"
        );
    }
}

/// Gauge R&R by ANOVA against the reference: studies of many shapes (2 to 40 parts, 2 to 4
/// appraisers, 2 to 5 trials) with part spread, appraiser offsets, interaction and noise in
/// different proportions, with and without a tolerance, and shapes that cannot be analysed.
#[test]
fn gauge_rr_agrees_with_the_numpy_reference() {
    use dpsa_spc::msa::gauge_rr;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(25);
    let normal = Normal::new(0.0, 1.0).unwrap();
    // Values, parts, appraisers, trials, tolerance.
    type Study = (Vec<f64>, usize, usize, usize, Option<f64>);
    let mut studies: Vec<Study> = Vec::new();
    for k in 0..40 {
        let (p, a, r) = (
            [2, 5, 10, 40][k % 4],
            [2, 3, 4][k % 3],
            [2, 3, 5][(k / 4) % 3],
        );
        let (sp, sa, si, se) = (
            [0.0, 1.0, 10.0][k % 3],
            [0.0, 0.5, 3.0][(k / 3) % 3],
            [0.0, 0.3][(k / 9) % 2],
            [0.01, 1.0][(k / 2) % 2],
        );
        let parts: Vec<f64> = (0..p)
            .map(|_| 100.0 + sp * normal.sample(&mut rng))
            .collect();
        let apps: Vec<f64> = (0..a).map(|_| sa * normal.sample(&mut rng)).collect();
        let mut x = Vec::new();
        for pp in &parts {
            for aa in &apps {
                let i = si * normal.sample(&mut rng);
                for _ in 0..r {
                    x.push(pp + aa + i + se * normal.sample(&mut rng));
                }
            }
        }
        studies.push((x, p, a, r, (k % 5 != 0).then_some(90.0)));
    }
    studies.push((vec![1.0; 6], 1, 2, 3, None));
    studies.push((vec![1.0, 2.0, 3.0, 4.0], 2, 2, 1, None));
    let input = json!({"cases": studies.iter().map(|(x, p, a, r, t)| json!({
        "kind": "msa", "x": x, "parts": p, "appraisers": a, "trials": r, "tolerance": t,
    })).collect::<Vec<_>>()});
    let out = run_reference(&input);
    let results = out["results"].as_array().unwrap();
    assert_eq!(results.len(), studies.len());
    for (k, ((x, p, a, r, t), res)) in studies.iter().zip(results).enumerate() {
        let what = format!("study {k}");
        let Ok(g) = gauge_rr(x, *p, *a, *r, *t) else {
            assert!(
                res["grr"].is_null(),
                "{what}: an error here, a result in numpy"
            );
            continue;
        };
        for (i, (m, d)) in g.ms.iter().zip(g.df).enumerate() {
            close(&format!("{what} ms {i}"), Some(*m), &res["ms"][i], 0.0);
            close(&format!("{what} df {i}"), Some(d), &res["df"][i], 0.0);
        }
        for (name, v) in [
            ("repeatability", g.repeatability),
            ("reproducibility", g.reproducibility),
            ("appraiser", g.appraiser),
            ("interaction", g.interaction),
            ("grr", g.grr),
            ("part", g.part),
            ("total", g.total),
        ] {
            close(&format!("{what} {name}"), Some(v), &res[name], 1e-12);
        }
        close(
            &format!("{what} pct_tolerance"),
            g.pct_tolerance,
            &res["pct_tolerance"],
            0.0,
        );
        close(
            &format!("{what} pct_total"),
            g.pct_total,
            &res["pct_total"],
            0.0,
        );
        assert_eq!(
            g.ndc,
            res["ndc"].as_u64(),
            "{what} ndc: {:?} against {}",
            g.ndc,
            res["ndc"]
        );
    }
}
